"""Recorded robot episodes (real cameras, teleoperation) and their import into a data set.

A recording is a directory::

    REC/recording.json        what does not change: the task, and per camera its intrinsics
                              (fx, fy, cx, cy), depth_scale, mount ("fixed" or "hand") and pose
                              (fixed: camera-to-base 4x4; hand: the hand-eye transform, the
                              camera's 4x4 pose on the hand), all in OpenCV's camera axes
    REC/episode_0000.npz      one episode, T steps: for each camera "<name>.depth" (T, H, W)
                              and optionally "<name>.rgb" (T, H, W, 3); "state" (T, D), the
                              robot's proprioception the policy will read (agent_pos); "action"
                              (T, A), the commanded action; "hand_pose" (T, 4, 4), the hand's
                              pose in the base frame (needed with a hand-mounted camera);
                              optionally "success" (T,) bool

:class:`Recorder` writes it step by step (an episode is written when it ends, atomically);
:func:`import_recording` fuses each step's frames with the same crop and sampling as the
simulated envs (:func:`~d2a_envs.rgbd.fuse_frames`) into a data set any trainer here reads.

Example::

    recorder = Recorder("rec/pick", task="pick-place", cameras={"kinect": kinect, "wrist": wrist})
    recorder.add(depths={"kinect": d0, "wrist": d1}, state=q, action=a, hand_pose=T_base_hand, success=done)
    recorder.end_episode()
    import_recording("rec/pick", "data/pick", crop_box=box, num_points=1024)
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict

from collectors.atomic import atomic_savez, atomic_write_text
from collectors.storage import CollectionRecord, DatasetError, DemoDataset, EpisodeRecord
from d2a_envs.rgbd import CameraIntrinsics, RGBDFrame, eye_in_hand_pose, fuse_frames
from d2a_envs.sampling import CropBox

MOUNTS = ("fixed", "hand")


@dataclass(frozen=True)
class RecordedCamera:
    """A camera of a recording: intrinsics, depth scale, where it is mounted and its pose there."""

    intrinsics: CameraIntrinsics
    pose: tuple[tuple[float, ...], ...]  # 4x4: camera-to-base (fixed) or the camera's pose on the hand
    mount: str = "fixed"
    depth_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.mount not in MOUNTS:
            raise ValueError(f"mount must be one of {MOUNTS}, not {self.mount!r}")
        object.__setattr__(self, "pose", tuple(tuple(float(v) for v in row) for row in np.asarray(self.pose)))
        if np.shape(self.pose) != (4, 4):
            raise ValueError(f"a camera pose is a 4x4 transform, got shape {np.shape(self.pose)}")

    def frame(self, depth: np.ndarray, hand_pose: np.ndarray | None, rgb: np.ndarray | None = None) -> RGBDFrame:
        """This camera's frame at one step (a hand camera needs the hand's pose then)."""
        pose = np.asarray(self.pose)
        if self.mount == "hand":
            if hand_pose is None:
                raise ValueError("a hand-mounted camera needs the hand's pose at every step (hand_pose)")
            pose = eye_in_hand_pose(hand_pose, pose)
        return RGBDFrame(depth, self.intrinsics, pose, rgb, self.depth_scale)


def _read_cameras(raw: dict[str, Any]) -> dict[str, RecordedCamera]:
    return {name: RecordedCamera(CameraIntrinsics(**spec["intrinsics"]), spec["pose"], spec["mount"],
                                 spec["depth_scale"]) for name, spec in raw.items()}


class Recorder:
    """Writes a recording: ``add`` one step at a time, ``end_episode`` to store the episode."""

    def __init__(self, directory: str | Path, task: str, cameras: dict[str, RecordedCamera]) -> None:
        if not cameras:
            raise ValueError("a recording needs at least one camera")
        self.directory, self.cameras = Path(directory), cameras
        self.directory.mkdir(parents=True, exist_ok=True)
        meta = self.directory / "recording.json"
        spec = {"task": task, "cameras": {name: asdict(camera) for name, camera in cameras.items()}}
        if meta.exists() and json.loads(meta.read_text()) != json.loads(json.dumps(spec)):
            raise ValueError(f"{self.directory} holds a recording of another task or other cameras")
        atomic_write_text(meta, json.dumps(spec, indent=1))
        self.episodes = len(list(self.directory.glob("episode_*.npz")))
        self._steps: list[dict[str, np.ndarray]] = []

    def add(self, depths: dict[str, np.ndarray], state: np.ndarray, action: np.ndarray,
            hand_pose: np.ndarray | None = None, rgbs: dict[str, np.ndarray] | None = None,
            success: bool = False) -> None:
        """One step: every camera's depth (and colour), the robot's state, the action commanded."""
        if set(depths) != set(self.cameras):
            raise ValueError(f"a step needs the depth of cameras {sorted(self.cameras)}, got {sorted(depths)}")
        step = {f"{name}.depth": np.asarray(depth) for name, depth in depths.items()}
        step |= {f"{name}.rgb": np.asarray(rgb) for name, rgb in (rgbs or {}).items()}
        step |= {"state": np.asarray(state, dtype=np.float32), "action": np.asarray(action, dtype=np.float32),
                 "success": np.asarray(bool(success))}
        if hand_pose is not None:
            step["hand_pose"] = np.asarray(hand_pose, dtype=np.float64)
        self._steps.append(step)

    def end_episode(self) -> Path:
        """Write the steps added since the last episode as the next ``episode_NNNN.npz``."""
        if not self._steps:
            raise ValueError("no step was added to this episode")
        path = self.directory / f"episode_{self.episodes:04d}.npz"
        atomic_savez(path, **{key: np.stack([step[key] for step in self._steps]) for key in self._steps[0]})
        self.episodes += 1
        self._steps = []
        return path


def import_recording(
    directory: str | Path, out: str | Path, crop_box: CropBox, num_points: int = 1024,
    env_kwargs: dict[str, Any] | None = None, overwrite: bool = False, seed: int = 0,
) -> DemoDataset:
    """A data set at ``out`` holding every recorded episode, each step's frames fused into
    ``num_points`` points inside ``crop_box``; ``env_kwargs`` records the simulated env whose
    clouds match (default: the crop box and point count)."""
    directory = Path(directory)
    try:
        spec = json.loads((directory / "recording.json").read_text())
    except FileNotFoundError as error:
        raise DatasetError(f"{directory} is not a recording (no recording.json)") from error
    cameras, task = _read_cameras(spec["cameras"]), spec["task"]
    episodes = sorted(directory.glob("episode_*.npz"))
    if not episodes:
        raise DatasetError(f"{directory} holds no recorded episode")
    box = CropBox.from_any(crop_box)
    rng = np.random.default_rng(seed)
    loaded = [dict(np.load(path)) for path in episodes]
    dataset = DemoDataset.create(out, capacity=sum(len(episode["action"]) for episode in loaded), overwrite=overwrite)
    dataset.metadata.tasks[task] = env_kwargs or {"crop_box": [list(box.low), list(box.high)], "num_points": num_points}
    dataset.metadata.collections.append(CollectionRecord(task=task, seed=-1, kept=len(loaded)))  # -1: recorded
    for index, episode in enumerate(loaded):
        steps = len(episode["action"])
        clouds = np.stack([fuse_frames(
            [camera.frame(episode[f"{name}.depth"][t], episode["hand_pose"][t] if "hand_pose" in episode else None)
             for name, camera in cameras.items()], box, num_points, rng).points for t in range(steps)])
        success = torch.as_tensor(episode.get("success", np.zeros(steps, dtype=bool)))
        frames = TensorDict({
            "point_cloud": torch.from_numpy(clouds), "agent_pos": torch.from_numpy(episode["state"]),
            "state": torch.from_numpy(episode["state"]), "action": torch.from_numpy(episode["action"]),
            "reward": torch.zeros(steps), "success": success, "episode": torch.full((steps,), index),
            "step": torch.arange(steps),
        }, batch_size=[steps])
        dataset.add_episode(frames, EpisodeRecord(
            index=index, task=task, start=0, length=0, success=bool(success.any()), episode_return=0.0,
            collection=0, attempt=index, min_points_in_crop=num_points))
    return dataset
