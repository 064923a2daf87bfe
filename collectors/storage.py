"""Demonstration data sets on disk: a TorchRL replay buffer plus a metadata file.

Layout of a data set directory::

    DIR/d2a_dataset.json     metadata: format, tasks and env kwargs, episodes, seeds, versions
    DIR/buffer/              TensorDictReplayBuffer over LazyMemmapStorage (``rb.dumps``)

One row of the buffer is one control step: the observation before the step
(``point_cloud``, ``agent_pos``, ``state``, and ``image`` in a data set collected with one),
the ``action`` taken, the step's ``reward`` and ``success``, and where it sits (``episode``,
``step``). Episodes are stored contiguously.
The metadata file is the source of truth: it is replaced atomically after each complete
episode, so a collection killed midway leaves every finished episode readable, and rows
written after the last metadata update are ignored (and overwritten by ``--append``).
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import asdict, dataclass, field, replace
from importlib import metadata as package_metadata
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyMemmapStorage, TensorDictReplayBuffer

from collectors.atomic import DirectoryBusyError, atomic_write_text, holds_only_lock, is_lock_file, writer_active
from d2a_envs.factory import env_crop_box
from d2a_envs.wrappers import IMAGE_KEY

# A rollout's expert action where the executed ``action`` was perturbed (DART noise): the label stored.
EXPERT_ACTION_KEY = "expert_action"

FORMAT = "d2a-demonstrations"
# v2: clouds show the scene's visible sites (goal markers); v1 clouds did not.
FORMAT_VERSION = 2
METADATA_FILE = "d2a_dataset.json"
BUFFER_DIR = "buffer"
FRAME_KEYS = ("point_cloud", "agent_pos", "state", "action", "reward", "success", "episode", "step")
# Stored where the env had them (``rgb_image_size``): in every row of a data set, or in none.
OPTIONAL_FRAME_KEYS = (IMAGE_KEY,)
# Stored clouds are float32: a point on the box's face may round a little past it.
_BOX_TOLERANCE = 1e-3
VERSIONED_PACKAGES = ("d2a", "metaworld", "mujoco", "gymnasium", "gymnasium-robotics", "torch", "torchrl", "tensordict")


class DatasetError(ValueError):
    """A directory that is not, or no longer, a readable D2A data set."""


@dataclass
class EpisodeRecord:
    """Where one stored episode lives and how it went."""

    index: int
    task: str
    start: int
    length: int
    success: bool
    episode_return: float
    collection: int
    attempt: int
    min_points_in_crop: int


@dataclass
class CollectionRecord:
    """One run of ``d2a collect`` into this data set (``--append`` adds another)."""

    task: str
    seed: int
    attempts: int = 0
    kept: int = 0
    action_noise: float = 0.0  # std of the noise added to the expert's actions (0: demonstrations)
    keep_failures: bool = False  # every attempt stored, not only the successes
    expert: str | None = None  # scripted, controller or planner (None: collected before this was recorded)
    dart_noise: float = 0.0  # std of the noise on the executed actions; the stored labels are the expert's
    student: str | None = None  # the policy that acted while the expert labelled (DAgger), if any
    student_labels: bool = True  # False: the student's own actions were stored, no expert labels

    @property
    def rollouts(self) -> bool:
        """Whether this collection holds rollouts (noisy, failed or a policy's own, unlabelled),
        not demonstrations; a student's labelled episodes, failures included, carry the expert's
        labels and train policies."""
        if self.student is not None:
            return not self.student_labels
        return self.action_noise > 0 or self.keep_failures


@dataclass
class DatasetMetadata:
    """Everything needed to read and to reproduce a data set."""

    tasks: dict[str, dict[str, Any]] = field(default_factory=dict)  # task -> env kwargs
    episodes: list[EpisodeRecord] = field(default_factory=list)
    collections: list[CollectionRecord] = field(default_factory=list)
    capacity: int = 0
    versions: dict[str, str] = field(default_factory=dict)
    format: str = FORMAT
    format_version: int = FORMAT_VERSION

    @property
    def num_frames(self) -> int:
        return sum(episode.length for episode in self.episodes)

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=1)

    @classmethod
    def from_json(cls, text: str) -> DatasetMetadata:
        raw = json.loads(text)
        raw["episodes"] = [EpisodeRecord(**e) for e in raw.get("episodes", [])]
        raw["collections"] = [CollectionRecord(**c) for c in raw.get("collections", [])]
        return cls(**raw)


def package_versions() -> dict[str, str]:
    """Installed versions of the packages that shape the data."""
    versions = {}
    for name in VERSIONED_PACKAGES:
        try:
            versions[name] = package_metadata.version(name)
        except package_metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def _check_buffer_files(storage: Path, capacity: int) -> None:
    """Refuse memory-mapped files that do not match their recorded layout, before anything maps them.

    Mapping a truncated file would silently re-grow it with zeros (and train on zero clouds).
    """
    layout_path = storage / "meta.json"
    try:
        layout = json.loads(layout_path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise DatasetError(f"{layout_path} is unreadable ({error}): the data set is damaged") from error
    for key in FRAME_KEYS + tuple(key for key in OPTIONAL_FRAME_KEYS if key in layout):
        entry = layout.get(key)
        path = storage / f"{key}.memmap"
        if not isinstance(entry, dict) or not path.is_file():
            raise DatasetError(f"{path} is missing: the data set is damaged")
        dtype = getattr(torch, str(entry.get("dtype", "")).removeprefix("torch."), None)
        shape = entry.get("shape") or [0]
        if not isinstance(dtype, torch.dtype) or shape[0] != capacity:
            raise DatasetError(f"{layout_path} records {key} as {shape} {dtype}, not {capacity} rows: damaged")
        expected, size = math.prod(shape) * dtype.itemsize, path.stat().st_size
        if size != expected:
            raise DatasetError(f"{path} holds {size} bytes where {shape} of {dtype} need {expected}: the data set "
                               f"is damaged (truncated or overwritten)")


def _new_buffer(directory: Path, capacity: int) -> TensorDictReplayBuffer:
    storage = LazyMemmapStorage(capacity, scratch_dir=directory / BUFFER_DIR / "storage", existsok=True)
    return TensorDictReplayBuffer(storage=storage, batch_size=1)


def _looks_foreign(directory: Path) -> bool:
    return (directory.exists() and not holds_only_lock(directory)
            and not DemoDataset.is_dataset(directory) and not (directory / BUFFER_DIR).exists())


def _refuse_if_foreign(directory: Path) -> None:
    """The check for a caller that holds the directory's writer lock (no other writer can be in it)."""
    if _looks_foreign(directory):
        raise DatasetError(f"refusing to write into {directory}: it holds files but is not a D2A data set")


def refuse_foreign(directory: Path) -> None:
    """Refuse to write into a directory that holds files but is not a D2A data set.

    A directory whose writer lock a live process holds is busy, not foreign: it may be a data set
    being created (its first files appear before its metadata). That raises
    :class:`~collectors.atomic.DirectoryBusyError`, which a caller can wait out."""
    if _looks_foreign(directory) and writer_active(directory):
        raise DirectoryBusyError.of(directory)
    _refuse_if_foreign(directory)  # looked again: its writer may have finished between the two looks


class DemoDataset:
    """A data set directory opened for reading or appending.

    Example:
        >>> dataset = DemoDataset.open("data/hammer")
        >>> len(dataset.metadata.episodes), dataset.num_frames
        (10, 2000)
        >>> frames = dataset.frames()       # TensorDict of every stored step, in order
    """

    def __init__(self, directory: Path, metadata: DatasetMetadata, buffer: TensorDictReplayBuffer) -> None:
        self.directory = directory
        self.metadata = metadata
        self.buffer = buffer

    # --- opening --------------------------------------------------------------------------

    @staticmethod
    def is_dataset(directory: str | Path) -> bool:
        return (Path(directory) / METADATA_FILE).is_file()

    @classmethod
    def create(cls, directory: str | Path, capacity: int, overwrite: bool = False) -> DemoDataset:
        """A new, empty data set with room for ``capacity`` steps.

        An existing non-empty directory is refused unless ``overwrite``; a writer lock held on
        it (:func:`collectors.atomic.exclusive_writer`) survives the overwrite.
        """
        directory = Path(directory)
        if directory.exists() and not holds_only_lock(directory):
            if not overwrite:
                raise DatasetError(f"{directory} already holds files; pass --append to add to it or --overwrite")
            _refuse_if_foreign(directory)  # the caller may hold the lock: its own lock is not another writer
            for entry in directory.iterdir():
                if not is_lock_file(entry):
                    shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
        directory.mkdir(parents=True, exist_ok=True)
        dataset = cls(directory, DatasetMetadata(capacity=capacity, versions=package_versions()),
                      _new_buffer(directory, capacity))
        dataset._save_metadata()
        return dataset

    @classmethod
    def open(cls, directory: str | Path) -> DemoDataset:
        """Open an existing data set; a missing, foreign or truncated one gets a clear error."""
        directory = Path(directory)
        if not directory.is_dir():
            raise DatasetError(f"no data set at {directory}: the directory does not exist")
        if not cls.is_dataset(directory):
            raise DatasetError(f"{directory} is not a D2A data set: {METADATA_FILE} is missing")
        try:
            metadata = DatasetMetadata.from_json((directory / METADATA_FILE).read_text())
        except (json.JSONDecodeError, TypeError, KeyError) as error:
            raise DatasetError(f"{directory / METADATA_FILE} is unreadable: {error}") from error
        if metadata.format != FORMAT or metadata.format_version != FORMAT_VERSION:
            raise DatasetError(
                f"{directory} has format {metadata.format!r} v{metadata.format_version}; "
                f"this version of D2A reads {FORMAT!r} v{FORMAT_VERSION}: collect it again"
            )
        buffer = _new_buffer(directory, metadata.capacity)
        if metadata.episodes:
            if not (directory / BUFFER_DIR / "storage" / "storage_metadata.json").is_file():
                raise DatasetError(f"{directory} is truncated: its metadata lists episodes but {BUFFER_DIR}/ is empty")
            _check_buffer_files(directory / BUFFER_DIR / "storage", metadata.capacity)
            buffer.loads(directory / BUFFER_DIR)
            if len(buffer) < metadata.num_frames:
                raise DatasetError(
                    f"{directory} is truncated: the metadata lists {metadata.num_frames} steps, "
                    f"the buffer holds {len(buffer)}"
                )
        dataset = cls(directory, metadata, buffer)
        dataset._rewind_to_metadata()
        return dataset

    @classmethod
    def open_for_training(cls, directory: str | Path, *, current_crop: bool = True) -> DemoDataset:
        """Open a data set a trainer can use: at least one episode, every value finite and, with
        ``current_crop``, collected clouds inside the boxes their envs crop to now (an export,
        which carries the clouds as they were collected, passes ``False``)."""
        dataset = cls.open(directory)
        if not dataset.metadata.episodes:
            raise DatasetError(f"{directory} holds no episodes (did every collection attempt fail?)")
        dataset.check_finite()
        if current_crop:
            dataset.check_crop_boxes()
        return dataset

    def episode_counts(self) -> dict[str, int]:
        """Stored episodes per task."""
        counts = dict.fromkeys(self.metadata.tasks, 0)
        for episode in self.metadata.episodes:
            counts[episode.task] += 1
        return counts

    def holds_exactly(self, demos: int | None) -> bool:
        """Whether ``demos`` episodes per task are every episode (``None``: all of them, trivially):
        a trainer asked for them records the run as one on the whole data set."""
        return demos is None or set(self.episode_counts().values()) == {demos}

    def rollout_episodes(self) -> list[int]:
        """Ids of the episodes of rollout collections (noisy or kept failures): no policy trains on them."""
        return [e.index for e in self.metadata.episodes if self.metadata.collections[e.collection].rollouts]

    def demonstrations(self) -> DemoDataset:
        """A read-only view without the rollout episodes (the data set itself when it has none);
        they must follow the demonstrations in the storage (collect rollouts after them)."""
        rollouts = set(self.rollout_episodes())
        if not rollouts:
            return self
        episodes = [e for e in self.metadata.episodes if e.index not in rollouts]
        if episodes != self.metadata.episodes[: len(episodes)]:
            raise DatasetError(f"{self.directory}: rollouts were collected before demonstrations; collect the "
                               "demonstrations first")
        return DemoDataset(self.directory, replace(self.metadata, episodes=episodes), self.buffer)

    def first_episodes(self, demos: int) -> DemoDataset:
        """A read-only view of the first ``demos`` episodes of each task, so that runs on 1, 2,
        5, 10 ... demonstrations of one collection train on nested sets. The view's episodes must
        lead the storage (always true of a single-task data set); DatasetError where a task has
        fewer episodes or they do not."""
        episodes, kept = [], dict.fromkeys(self.metadata.tasks, 0)
        for episode in self.metadata.episodes:
            if kept[episode.task] < demos:
                episodes.append(episode)
                kept[episode.task] += 1
        short = {task: count for task, count in kept.items() if count < demos}
        if short:
            raise DatasetError(f"{self.directory} holds fewer than {demos} episodes of {short} (task: episodes)")
        if episodes != self.metadata.episodes[: len(episodes)]:
            raise DatasetError(f"{self.directory}: the first {demos} episodes of each task are not the first in "
                               "the storage; collect each task into its own data set to train on a prefix")
        return DemoDataset(self.directory, replace(self.metadata, episodes=episodes), self.buffer)

    # --- writing --------------------------------------------------------------------------

    def _rewind_to_metadata(self) -> None:
        """Forget rows written after the last metadata update (a killed collection)."""
        frames = self.metadata.num_frames
        self.buffer.storage._len = frames
        self.buffer.writer._cursor = frames

    def _save_metadata(self) -> None:
        atomic_write_text(self.directory / METADATA_FILE, self.metadata.to_json())

    def ensure_capacity(self, extra_frames: int) -> None:
        """Grow the storage (by copying) if ``extra_frames`` more steps would not fit."""
        needed = self.metadata.num_frames + extra_frames
        if needed <= self.metadata.capacity:
            return
        frames = self.frames().clone() if self.metadata.num_frames else None
        shutil.rmtree(self.directory / BUFFER_DIR, ignore_errors=True)
        self.buffer = _new_buffer(self.directory, needed)
        if frames is not None:
            self.buffer.extend(frames)
            self.buffer.dumps(self.directory / BUFFER_DIR)
        self.metadata.capacity = needed
        self._save_metadata()

    def add_episode(self, frames: TensorDictBase, record: EpisodeRecord) -> None:
        """Store one complete episode (rows = steps, keys = :data:`FRAME_KEYS`), then commit it
        by rewriting the metadata: the episode exists only once that succeeded."""
        missing = [key for key in FRAME_KEYS if key not in frames.keys()]
        if missing:
            raise ValueError(f"episode frames lack {missing}")
        keys = FRAME_KEYS + tuple(key for key in OPTIONAL_FRAME_KEYS if key in frames.keys())
        stored = self.frame_keys
        if self.num_frames and set(keys) != set(stored):
            raise DatasetError(f"{self.directory} stores {sorted(stored)} per step; this episode has "
                               f"{sorted(keys)} (images are stored in every episode of a data set or in none)")
        self.ensure_capacity(frames.shape[0])
        record.start, record.length = self.metadata.num_frames, frames.shape[0]
        self.buffer.extend(frames.select(*keys))
        self.buffer.dumps(self.directory / BUFFER_DIR)
        self.metadata.episodes.append(record)
        self._save_metadata()

    def commit(self) -> None:
        """Save the metadata (collection counters) without adding an episode."""
        self._save_metadata()

    # --- reading --------------------------------------------------------------------------

    @property
    def num_frames(self) -> int:
        return self.metadata.num_frames

    @property
    def frame_keys(self) -> tuple[str, ...]:
        """What each stored step holds: :data:`FRAME_KEYS`, plus ``image`` where the data set has them."""
        stored = self.frames().keys() if self.num_frames else ()
        return FRAME_KEYS + tuple(key for key in OPTIONAL_FRAME_KEYS if key in stored)

    def frames(self) -> TensorDict:
        """Every stored step in order, as a memory-mapped TensorDict (no copy)."""
        return self.buffer.storage._storage[: self.num_frames]

    def check_finite(self) -> None:
        """Refuse non-finite values in any float field (a NaN cloud would train into NaN weights)."""
        frames = self.frames()
        for key in FRAME_KEYS:
            values = frames[key]
            if not values.is_floating_point():
                continue
            bad = ~torch.isfinite(values.reshape(len(values), -1)).all(dim=1)
            if bad.any():
                first = int(bad.nonzero()[0])
                episode = int(frames["episode"][first])
                raise DatasetError(f"{self.directory}: {key} holds non-finite values in {int(bad.sum())} steps "
                                   f"(first: episode {episode}, step {int(frames['step'][first])}); collect it again")

    def check_crop_boxes(self) -> None:
        """Refuse collected clouds that leave the box their task's env crops to now.

        A collection here keeps only points inside its env's box, so points outside it mean the
        clouds came from another box (an older default): a policy would train on clouds that its
        evaluations never show. Imported and recorded episodes (collection seed -1) are not checked.
        """
        frames = self.frames()
        for task, env_kwargs in self.metadata.tasks.items():
            starts = [e.start for e in self.metadata.episodes
                      if e.task == task and self.metadata.collections[e.collection].seed >= 0]
            if not starts:
                continue
            box = env_crop_box(task, env_kwargs)
            points = frames["point_cloud"][torch.tensor(starts)][..., :3].reshape(-1, 3).numpy()
            low, high = np.array(box.low) - _BOX_TOLERANCE, np.array(box.high) + _BOX_TOLERANCE
            outside = ~np.all((points >= low) & (points <= high), axis=1)
            if outside.any():
                raise DatasetError(
                    f"{self.directory}: {int(outside.sum())} points of {task}'s first frames lie outside the box its "
                    f"env crops to now (low={box.low}, high={box.high}): the clouds were collected with another "
                    "box; collect them again")

    def episode(self, index: int) -> TensorDict:
        """The steps of stored episode ``index``."""
        record = self.metadata.episodes[index]
        return self.buffer.storage._storage[record.start : record.start + record.length]

    def size_on_disk(self) -> int:
        """Bytes the directory really occupies (memory maps are sparse files)."""
        return sum(os.stat(p).st_blocks * 512 for p in self.directory.rglob("*") if p.is_file())


def episode_frames(rollout: TensorDictBase, episode_index: int) -> TensorDict:
    """Turn one TorchRL trajectory (batch = steps) into the stored row layout."""
    steps = rollout.shape[0]
    images = {IMAGE_KEY: rollout[IMAGE_KEY]} if IMAGE_KEY in rollout.keys() else {}
    return TensorDict(
        {
            **images,
            "point_cloud": rollout["point_cloud"],
            "agent_pos": rollout["agent_pos"],
            "state": rollout["observation"],
            "action": rollout.get(EXPERT_ACTION_KEY, rollout["action"]),  # with DART noise: the expert's label
            "reward": rollout["next", "reward"].reshape(steps),
            "success": rollout["next", "success"].reshape(steps),
            "episode": torch.full((steps,), episode_index, dtype=torch.int64),
            "step": torch.arange(steps, dtype=torch.int64),
        },
        batch_size=[steps],
    )


def describe(dataset: DemoDataset) -> str:
    """A human-readable summary: per task episodes, attempts, lengths, success, point counts, size."""
    meta = dataset.metadata
    lines = [f"{dataset.directory}: {len(meta.episodes)} episodes, {meta.num_frames} steps, "
             f"{dataset.size_on_disk() / 2**20:.1f} MiB on disk (format {meta.format} v{meta.format_version})"]
    if meta.num_frames:
        frames = dataset.frames()
        keys = ("point_cloud", "agent_pos", "state", "action") + tuple(
            key for key in OPTIONAL_FRAME_KEYS if key in frames.keys())
        shapes = {key: tuple(frames[key].shape[1:]) for key in keys}
        lines.append(", ".join(f"{key} {shape}" for key, shape in shapes.items()))
    header = ("task", "kept", "tried", "length min/mean/max", "success", "min pts in crop")
    lines.append(f"{header[0]:<22} {header[1]:>5} {header[2]:>6} {header[3]:>20} {header[4]:>8} {header[5]:>16}")
    for task, env_kwargs in meta.tasks.items():
        episodes = [e for e in meta.episodes if e.task == task]
        tried = sum(c.attempts for c in meta.collections if c.task == task)
        lengths = [e.length for e in episodes] or [0]
        success = sum(e.success for e in episodes) / max(len(episodes), 1)
        points = min((e.min_points_in_crop for e in episodes), default=0)
        length = f"{min(lengths)}/{sum(lengths) / len(lengths):.1f}/{max(lengths)}"
        lines.append(f"{task:<22} {len(episodes):>5} {tried:>6} {length:>20} {success:>8.0%} {points:>16}")
        lines.append(f"  env kwargs: {env_kwargs}")
    lines.append("versions: " + ", ".join(f"{k} {v}" for k, v in meta.versions.items()))
    return "\n".join(lines)
