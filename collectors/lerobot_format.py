"""LeRobot data sets in (``d2a data import --lerobot``).

A LeRobot data set, in its on-disk format v2.0, v2.1 or v3.0, is a directory::

    meta/info.json            codebase_version, fps, features (per column: dtype, shape), data_path
                              (the data files' name template), chunks_size (v2: episodes per chunk)
    meta/episodes.jsonl       v2: a line per episode: episode_index, tasks, length
    meta/episodes/chunk-XXX/file-XXX.parquet
                              v3: a row per episode: episode_index, tasks, length and the data file
                              holding its steps (data/chunk_index, data/file_index)
    data/chunk-XXX/episode_XXXXXX.parquet   v2: one episode per file
    data/chunk-XXX/file-XXX.parquet         v3: several episodes per file
    videos/...                              video-encoded features

A row of a data file is one step: ``episode_index``, ``frame_index`` (the step in its episode),
``index``, ``timestamp``, ``task_index``, then a column per feature: ``action``,
``observation.state``, other ``observation.*``, optionally ``next.reward`` and ``next.success``.

Import maps ``observation.state`` (or ``state_key``) to ``agent_pos`` and to ``state`` (or
``full_state_key`` there), ``action`` to ``action``, ``next.reward`` to ``reward`` (0 without it)
and ``next.success`` to the per-step success; without ``next.success`` every episode counts as a
success and each step reads False, as with DP3 files (:mod:`collectors.dp3_format`). The clouds
come from the data set itself: a point-cloud feature ((P, 3) or (P, 6): xyz kept, P the point
count), ``observation.point_cloud`` / ``observation.pointcloud`` or named by ``cloud_key``; or a
depth feature stored as an array column ((H, W) or (H, W, 1), ``observation.depth`` or
``depth_key``) with a camera file giving its intrinsics and camera-to-base pose, each step's depth
then fused with the envs' own crop and sampling (:func:`~d2a_envs.rgbd.fuse_frames`), as a
recording's is (:func:`~collectors.recording.import_recording`). The camera file holds the keys
of a fixed camera in a recording::

    {"intrinsics": {"fx": 615.0, "fy": 615.0, "cx": 320.0, "cy": 240.0}, "pose": [[...], ..., [0, 0, 0, 1]]}

Refused with a :class:`~collectors.storage.DatasetError`: other codebase versions, features stored
as video or images (their frames are not decoded here), and a data set with neither a cloud nor a
depth array with a camera file (the error lists its features).

Example::

    import_lerobot("pick_lerobot", "data/pick", task="pick-place")   # its observation.point_cloud
    import_lerobot("pick_lerobot", "data/pick", task="pick-place", camera="camera.json", depth_scale=0.001,
                   crop_box=box, num_points=1024)
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from collectors.recording import RecordedCamera
from collectors.storage import CollectionRecord, DatasetError, DemoDataset, EpisodeRecord
from d2a_envs.rgbd import CameraIntrinsics, fuse_frames
from d2a_envs.sampling import CropBox

VERSIONS = ("v2.0", "v2.1", "v3.0")
CLOUD_KEYS = ("observation.point_cloud", "observation.pointcloud")
DEPTH_KEY = "observation.depth"
REWARD_KEY, SUCCESS_KEY = "next.reward", "next.success"
NOT_DECODED = ("video", "image")  # dtypes whose frames live in video or image files, not in the columns
STEP_KEYS = ("episode_index", "frame_index")


def _pyarrow() -> Any:
    try:
        import pyarrow
        import pyarrow.parquet  # noqa: F401  (the submodule read_table lives in)
    except ImportError as error:  # an optional dependency: the ``lerobot`` extra
        message = "LeRobot data sets need pyarrow: pip install 'd2a[lerobot]' (or pip install pyarrow)"
        raise ImportError(message) from error
    return pyarrow


@dataclass
class LeRobotEpisodes:
    """What :func:`read_lerobot` read: the features (info.json's) and, per episode, its steps."""

    version: str
    features: dict[str, dict[str, Any]]
    episodes: list[dict[str, np.ndarray]]  # per episode: column -> (T, *shape)
    tasks: list[list[str]]  # per episode: its tasks in words


@dataclass(frozen=True)
class _EpisodeEntry:
    """Where one episode's steps are: its index, length, tasks and data file."""

    index: int
    length: int
    tasks: list[str]
    file: Path


def _read_info(path: Path) -> dict[str, Any]:
    """meta/info.json, refused unless of a codebase version read here."""
    try:
        info = json.loads((path / "meta" / "info.json").read_text())
    except FileNotFoundError as error:
        raise DatasetError(f"{path} is not a LeRobot data set: meta/info.json is missing") from error
    version = info.get("codebase_version")
    if version not in VERSIONS:
        raise DatasetError(f"{path}: LeRobot codebase_version {version!r} is not read here "
                           f"(reads {', '.join(VERSIONS)})")
    missing = [key for key in ("features", "data_path") if key not in info]
    if missing:
        raise DatasetError(f"{path}: meta/info.json lacks {missing}")
    return info


def _describe(features: dict[str, dict[str, Any]]) -> str:
    """The features as ``name (dtype shape)``, for errors."""
    return ", ".join(f"{key} ({spec.get('dtype')} {list(spec.get('shape', []))})" for key, spec in features.items())


def _episodes_v2(path: Path, info: dict[str, Any]) -> list[_EpisodeEntry]:
    """v2: meta/episodes.jsonl; episode e's file is in chunk e // chunks_size."""
    try:
        lines = (path / "meta" / "episodes.jsonl").read_text().splitlines()
    except FileNotFoundError as error:
        raise DatasetError(f"{path}: meta/episodes.jsonl is missing") from error
    per_chunk = int(info.get("chunks_size", 1000))
    entries = []
    for row in (json.loads(line) for line in lines if line.strip()):
        index = row["episode_index"]
        data_file = info["data_path"].format(episode_chunk=index // per_chunk, episode_index=index)
        entries.append(_EpisodeEntry(index, row["length"], list(row.get("tasks") or []), path / data_file))
    return entries


def _episodes_v3(path: Path, info: dict[str, Any]) -> list[_EpisodeEntry]:
    """v3: meta/episodes/chunk-*/file-*.parquet name each episode's data file."""
    parquet = _pyarrow().parquet
    files = sorted((path / "meta" / "episodes").glob("chunk-*/file-*.parquet"))
    if not files:
        raise DatasetError(f"{path}: meta/episodes/ holds no episode file (chunk-*/file-*.parquet)")
    columns = ["episode_index", "length", "tasks", "data/chunk_index", "data/file_index"]
    entries = []
    for file in files:
        _check_columns(parquet, file, columns)
        for row in parquet.read_table(file, columns=columns).to_pylist():
            data_file = info["data_path"].format(chunk_index=row["data/chunk_index"], file_index=row["data/file_index"])
            entries.append(_EpisodeEntry(row["episode_index"], row["length"], list(row["tasks"] or []),
                                         path / data_file))
    return entries


def _check_columns(parquet: Any, file: Path, columns: Sequence[str]) -> None:
    """Refuse a missing file, or one without ``columns``, naming what it lacks."""
    try:
        names = parquet.read_schema(file).names
    except FileNotFoundError as error:
        raise DatasetError(f"{file} is missing") from error
    missing = [key for key in columns if key not in names]
    if missing:
        raise DatasetError(f"{file} lacks the columns {missing}")


def _as_array(column: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    """A parquet column of scalars or (nested, fixed- or variable-size) lists as (rows, *shape)."""
    pyarrow = _pyarrow()
    values = column.combine_chunks()
    rows = len(values)
    while isinstance(values, (pyarrow.ExtensionArray, pyarrow.ListArray, pyarrow.LargeListArray,
                              pyarrow.FixedSizeListArray)):
        values = values.storage if isinstance(values, pyarrow.ExtensionArray) else values.flatten()
    if values.null_count:
        raise DatasetError(f"{name} has {values.null_count} missing values")
    flat = values.to_numpy(zero_copy_only=False)
    if flat.size != rows * math.prod(shape):
        raise DatasetError(f"{name} holds {flat.size} values in {rows} rows, not {list(shape)} per row")
    return flat.reshape(rows, *shape)


def _check_readable(path: Path, features: dict[str, dict[str, Any]], key: str) -> None:
    """Refuse a feature that is not there or whose values are not in the data files' columns."""
    if key not in features:
        raise DatasetError(f"{path} has no feature {key!r}; its features: {_describe(features)}")
    dtype = features[key].get("dtype")
    if dtype in NOT_DECODED:
        raise DatasetError(f"{path}: {key} is stored as {dtype} frames, which are not decoded here; "
                           f"an array column is read (its features: {_describe(features)})")
    if dtype == "string":
        raise DatasetError(f"{path}: {key} holds text, not numbers")


def _read_file(file: Path, features: dict[str, dict[str, Any]], columns: Sequence[str]) -> dict[str, np.ndarray]:
    """``columns`` (and the step keys) of one data file, each as (rows, *its feature's shape)."""
    parquet = _pyarrow().parquet
    keys = list(dict.fromkeys([*STEP_KEYS, *columns]))
    _check_columns(parquet, file, keys)
    table = parquet.read_table(file, columns=keys)
    shapes = {key: tuple(features[key]["shape"]) if key in features else () for key in keys}
    return {key: _as_array(table.column(key), shapes[key], f"{file}: {key}") for key in keys}


def _episode_steps(table: dict[str, np.ndarray], entry: _EpisodeEntry, columns: Sequence[str]) -> dict[str, np.ndarray]:
    """One episode's rows of a data file, refused unless they are its steps 0 .. length - 1 in order."""
    rows = table["episode_index"].reshape(-1) == entry.index
    frame_index = table["frame_index"].reshape(-1)[rows]
    if not np.array_equal(frame_index, np.arange(entry.length)):
        raise DatasetError(f"{entry.file}: episode {entry.index}'s rows are not its {entry.length} steps in order "
                           f"(frame_index {frame_index.tolist()})")
    return {key: table[key][rows] for key in columns}


def read_lerobot(path: str | Path, columns: Sequence[str] | None = None) -> LeRobotEpisodes:
    """The episodes of a LeRobot data set with ``columns`` (default: every feature stored as numbers),
    each episode checked against its recorded length."""
    path = Path(path)
    info = _read_info(path)
    features = info["features"]
    if columns is None:
        columns = [key for key, spec in features.items() if spec.get("dtype") not in (*NOT_DECODED, "string")]
    columns = list(dict.fromkeys(columns))
    for key in columns:
        _check_readable(path, features, key)
    entries = sorted((_episodes_v3 if info["codebase_version"] == "v3.0" else _episodes_v2)(path, info),
                     key=lambda entry: entry.index)
    if not entries:
        raise DatasetError(f"{path} holds no episode")
    by_file: dict[Path, list[_EpisodeEntry]] = {}
    for entry in entries:
        by_file.setdefault(entry.file, []).append(entry)
    steps: dict[int, dict[str, np.ndarray]] = {}
    for file, in_file in by_file.items():
        table = _read_file(file, features, columns)
        steps |= {entry.index: _episode_steps(table, entry, columns) for entry in in_file}
    return LeRobotEpisodes(info["codebase_version"], features, [steps[entry.index] for entry in entries],
                           [entry.tasks for entry in entries])


def _cloud_key(path: Path, features: dict[str, dict[str, Any]], cloud_key: str | None, depth_key: str | None,
               with_camera: bool) -> str:
    """The feature the clouds come from: the point-cloud feature named or found or, with a camera
    file, the depth feature; refused with the features listed when there is none."""
    if with_camera and cloud_key is not None:
        raise ValueError("give either a point-cloud feature (cloud_key) or a camera file for the depth, not both")
    if with_camera:
        key = depth_key or DEPTH_KEY
    else:
        key = cloud_key or next((k for k in CLOUD_KEYS if k in features), None)
    if key is None:
        depth = [k for k, spec in features.items() if "depth" in k and spec.get("dtype") not in NOT_DECODED]
        hint = f"; its depth {depth} needs a camera file (--camera) with intrinsics and pose" if depth else ""
        raise DatasetError(f"{path} holds no point cloud ({' or '.join(CLOUD_KEYS)}; name another with --cloud-key) "
                           f"and no depth array read with a camera file{hint}. Video and image features are not "
                           f"decoded here. Its features: {_describe(features)}")
    _check_readable(path, features, key)
    shape = tuple(features[key]["shape"])
    usable = (len(shape) == 2 or shape[2:] == (1,)) if with_camera else (len(shape) == 2 and shape[1] in (3, 6))
    if not usable:
        wanted = "(H, W) or (H, W, 1) depth" if with_camera else "(P, 3) or (P, 6) points"
        raise DatasetError(f"{path}: {key} has shape {list(shape)}, not {wanted}")
    return key


def _read_camera(path: str | Path, depth_scale: float) -> RecordedCamera:
    """A fixed camera from a JSON file: intrinsics (fx, fy, cx, cy) and camera-to-base pose (4x4)."""
    spec = json.loads(Path(path).read_text())
    if spec.get("mount", "fixed") != "fixed":
        raise ValueError(f"{path}: only a fixed camera is read (a hand camera needs the hand's pose at every step)")
    return RecordedCamera(CameraIntrinsics(**spec["intrinsics"]), spec["pose"], depth_scale=depth_scale)


def _fused_clouds(depths: np.ndarray, camera: RecordedCamera, box: CropBox, num_points: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """Each step's depth fused into ``num_points`` points in ``box``, and the fewest points any crop held."""
    readings = [fuse_frames([camera.frame(depth.reshape(depth.shape[:2]), None)], box, num_points, rng)
                for depth in depths]
    return np.stack([reading.points for reading in readings]), min(reading.num_in_crop for reading in readings)


def _frames(steps: dict[str, np.ndarray], clouds: np.ndarray, index: int, state_key: str,
            full_state_key: str) -> TensorDict:
    """One episode's rows as stored here; reward 0 and success False where the data set has no column."""
    length = len(steps["action"])
    reward = steps[REWARD_KEY].reshape(length) if REWARD_KEY in steps else np.zeros(length)
    success = steps[SUCCESS_KEY].reshape(length).astype(bool) if SUCCESS_KEY in steps else np.zeros(length, bool)
    return TensorDict({
        "point_cloud": torch.from_numpy(clouds),
        "agent_pos": torch.from_numpy(steps[state_key].astype(np.float32)),
        "state": torch.from_numpy(steps[full_state_key].astype(np.float32)),
        "action": torch.from_numpy(steps["action"].astype(np.float32)),
        "reward": torch.from_numpy(reward.astype(np.float32)), "success": torch.from_numpy(success),
        "episode": torch.full((length,), index, dtype=torch.int64), "step": torch.arange(length),
    }, batch_size=[length])


def import_lerobot(
    path: str | Path, out: str | Path, task: str, *, cloud_key: str | None = None, depth_key: str | None = None,
    camera: str | Path | None = None, depth_scale: float = 1.0, crop_box: CropBox | None = None,
    num_points: int = 1024, state_key: str = "observation.state", full_state_key: str | None = None,
    env_kwargs: dict[str, Any] | None = None, overwrite: bool = False, seed: int = 0,
) -> DemoDataset:
    """A data set at ``out`` holding the LeRobot data set's episodes as ``task``'s.

    Clouds: the point-cloud feature's (``cloud_key``, default the first of :data:`CLOUD_KEYS`
    there) or, given ``camera`` (a JSON file), the depth feature's (``depth_key``; ``depth *
    depth_scale`` in metres) fused into ``num_points`` points inside ``crop_box``. ``env_kwargs``:
    the ``gym.make`` options whose clouds match, recorded over the defaults (the file's point
    count; with depth, the crop box and point count).
    """
    from d2a_envs.tasks import get_task

    path, name = Path(path), get_task(task).name
    features = _read_info(path)["features"]
    key = _cloud_key(path, features, cloud_key, depth_key, camera is not None)
    outcomes = [column for column in (REWARD_KEY, SUCCESS_KEY) if column in features]
    read = read_lerobot(path, [key, state_key, full_state_key or state_key, "action", *outcomes])
    if camera is not None:
        if crop_box is None:
            raise ValueError("fusing depth into clouds needs crop_box (--crop-box)")
        box, fused_camera = CropBox.from_any(crop_box), _read_camera(camera, depth_scale)
        defaults: dict[str, Any] = {"crop_box": [list(box.low), list(box.high)], "num_points": num_points}
    else:
        defaults = {"num_points": int(features[key]["shape"][0])}
    rng = np.random.default_rng(seed)
    dataset = DemoDataset.create(out, capacity=sum(len(steps["action"]) for steps in read.episodes),
                                 overwrite=overwrite)
    dataset.metadata.tasks[name] = {**defaults, **(env_kwargs or {})}
    dataset.metadata.collections.append(CollectionRecord(task=name, seed=-1, kept=len(read.episodes)))  # -1: imported
    for index, steps in enumerate(read.episodes):
        if camera is not None:
            clouds, fewest = _fused_clouds(steps[key], fused_camera, box, num_points, rng)
        else:
            clouds, fewest = steps[key][..., :3].astype(np.float32), steps[key].shape[1]
        frames = _frames(steps, clouds, index, state_key, full_state_key or state_key)
        dataset.add_episode(frames, EpisodeRecord(
            index=index, task=name, start=0, length=0,
            success=bool(frames["success"].any()) if SUCCESS_KEY in steps else True,  # no column: kept as DP3's are
            episode_return=float(frames["reward"].sum()), collection=0, attempt=index, min_points_in_crop=int(fewest)))
    return dataset
