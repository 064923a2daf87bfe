"""DP3 / MP1 data sets in and out (``d2a data import`` / ``d2a data export``).

DP3 and MP1 store demonstrations as a zarr group (format 2, which both their zarr 2.x code and
zarr 3 read)::

    data/point_cloud   (T, P, 3 or 6) float32   xyz (+ rgb), world frame
    data/state         (T, D) float32           the robot's proprioception (``agent_pos``)
    data/full_state    (T, S) float32           Meta-World's full observation (optional)
    data/action        (T, A) float32
    data/img, data/depth                        images (optional; not read here)
    meta/episode_ends  (E,) int64               cumulative step counts: episode e ends before row ends[e]

Import maps ``data/state`` to ``agent_pos`` and ``data/full_state`` to ``state`` (``data/state``
again where there is none), keeps xyz of the clouds, and records every episode as a success
(DP3 and MP1 keep successful episodes only); per-step rewards and success are not stored there,
so they read 0 and False (trimming after the first success then keeps imported episodes whole).
Export writes the same keys from a data set here, so that DP3's or MP1's own code trains on it.
Clouds made elsewhere (another camera, crop box or point count) are not this toolkit's env
clouds: pass the env options that reproduce them, or evaluate with that in mind.

Example::

    import_dp3("metaworld_hammer_expert.zarr", "data/hammer_dp3", task="hammer")
    export_dp3("data/hammer", "hammer.zarr")
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from collectors.storage import CollectionRecord, DatasetError, DemoDataset, EpisodeRecord


def _zarr() -> Any:
    try:
        import zarr
    except ImportError as error:  # an optional dependency: the ``dp3`` extra
        raise ImportError("DP3-format data needs zarr: pip install 'd2a[dp3]' (or pip install zarr)") from error
    return zarr


def read_dp3(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of a DP3 / MP1 zarr that a data set here holds, checked for consistency."""
    zarr = _zarr()
    try:
        root = zarr.open_group(str(path), mode="r")
        data, ends = root["data"], np.asarray(root["meta/episode_ends"][:], dtype=np.int64)
    except (FileNotFoundError, KeyError) as error:
        raise DatasetError(f"{path} is not a DP3 zarr (needs data/ and meta/episode_ends): {error}") from error
    missing = [key for key in ("point_cloud", "state", "action") if key not in data]
    if missing:
        raise DatasetError(f"{path}: data/ lacks {missing}")
    arrays = {key: np.asarray(data[key][:]) for key in ("point_cloud", "state", "action")}
    arrays["full_state"] = np.asarray(data["full_state"][:]) if "full_state" in data else arrays["state"]
    steps = len(arrays["action"])
    if any(len(array) != steps for array in arrays.values()):
        raise DatasetError(f"{path}: its arrays differ in length ({ {k: len(v) for k, v in arrays.items()} })")
    if len(ends) == 0 or ends[-1] != steps or np.any(np.diff(np.concatenate([[0], ends])) <= 0):
        raise DatasetError(f"{path}: meta/episode_ends {ends.tolist()} does not split its {steps} steps into episodes")
    if arrays["point_cloud"].ndim != 3 or arrays["point_cloud"].shape[-1] < 3:
        raise DatasetError(f"{path}: data/point_cloud has shape {arrays['point_cloud'].shape}, not (T, P, >=3)")
    arrays["episode_ends"] = ends
    return arrays


def import_dp3(
    path: str | Path, out: str | Path, task: str, env_kwargs: dict[str, Any] | None = None, overwrite: bool = False,
) -> DemoDataset:
    """A data set at ``out`` holding the DP3 / MP1 zarr's episodes as ``task``'s.

    ``env_kwargs``: the ``gym.make`` options whose clouds match the file's (evaluation and the
    world model read them); default: the task's defaults at the file's point count.
    """
    from d2a_envs.tasks import get_task

    arrays = read_dp3(path)
    name = get_task(task).name
    clouds = arrays["point_cloud"][..., :3].astype(np.float32)
    kwargs = {"num_points": clouds.shape[1], **(env_kwargs or {})}
    ends = arrays["episode_ends"]
    dataset = DemoDataset.create(out, capacity=int(ends[-1]), overwrite=overwrite)
    dataset.metadata.tasks[name] = kwargs
    dataset.metadata.collections.append(CollectionRecord(task=name, seed=-1, kept=len(ends)))  # -1: not collected here
    for index, (start, end) in enumerate(zip(np.concatenate([[0], ends[:-1]]), ends, strict=True)):
        rows = slice(int(start), int(end))
        steps = int(end - start)
        frames = TensorDict({
            "point_cloud": torch.from_numpy(clouds[rows]),
            "agent_pos": torch.from_numpy(arrays["state"][rows].astype(np.float32)),
            "state": torch.from_numpy(arrays["full_state"][rows].astype(np.float32)),
            "action": torch.from_numpy(arrays["action"][rows].astype(np.float32)),
            "reward": torch.zeros(steps), "success": torch.zeros(steps, dtype=torch.bool),
            "episode": torch.full((steps,), index, dtype=torch.int64), "step": torch.arange(steps),
        }, batch_size=[steps])
        dataset.add_episode(frames, EpisodeRecord(
            index=index, task=name, start=0, length=0, success=True, episode_return=0.0, collection=0,
            attempt=index, min_points_in_crop=clouds.shape[1]))
    return dataset


def export_dp3(dataset_dir: str | Path, path: str | Path, overwrite: bool = False) -> Path:
    """Write a data set here as a DP3 / MP1 zarr (format 2) at ``path``; returns ``path``."""
    zarr = _zarr()
    dataset = DemoDataset.open_for_training(dataset_dir, current_crop=False)  # the clouds as collected
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True (--overwrite) to replace it")
    frames = dataset.frames()
    ends = np.cumsum([episode.length for episode in dataset.metadata.episodes]).astype(np.int64)
    root = zarr.open_group(str(path), mode="w", zarr_format=2)
    data = root.create_group("data")
    for key, source in (("point_cloud", "point_cloud"), ("state", "agent_pos"), ("full_state", "state"),
                        ("action", "action")):
        values = frames[source].numpy().astype(np.float32)
        data.create_array(key, data=values, chunks=(100, *values.shape[1:]))
    root.create_group("meta").create_array("episode_ends", data=ends)
    return path
