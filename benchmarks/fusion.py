"""Fusing real-camera frames into an observation (``d2a bench fusion``): two 640 x 480 depth
frames (a table plane seen from two poses, millimetres as RealSense and Kinect drivers give
them) back-projected, cropped and sampled to 1024 points, on one thread. The target for a
10 Hz control loop is 10 ms."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch

from benchmarks.latency import median_seconds
from d2a_envs.rgbd import CameraIntrinsics, RGBDFrame, frame_points, fuse_frames, pose_matrix
from d2a_envs.sampling import CropBox


@dataclass(frozen=True)
class FusionBenchConfig:
    """What ``d2a bench fusion`` times."""

    width: int = 640
    height: int = 480
    num_points: int = 1024
    repeats: int = 20


def _look_down(tilt_degrees: float, height: float) -> np.ndarray:
    """A camera ``height`` m above the origin, looking down, tilted about x."""
    angle = np.radians(180.0 + tilt_degrees)
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(angle), -np.sin(angle)], [0.0, np.sin(angle), np.cos(angle)]])
    return pose_matrix(rotation, np.array([0.0, 0.0, height]))


def frames(config: FusionBenchConfig) -> list[RGBDFrame]:
    """Two frames of the plane z = 0 (with a 10 cm box on it), depth in millimetres."""
    intrinsics = CameraIntrinsics(600.0, 600.0, config.width / 2 - 0.5, config.height / 2 - 0.5)
    result = []
    for tilt, height in ((0.0, 1.0), (20.0, 0.9)):
        pose = _look_down(tilt, height)
        u, v = np.meshgrid(np.arange(config.width), np.arange(config.height))
        rays = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy,
                         np.ones_like(u, dtype=float)], axis=-1) @ pose[:3, :3].T
        depth = -pose[2, 3] / rays[..., 2]  # where each ray meets z = 0
        depth[(np.abs(u - config.width / 2) < 40) & (np.abs(v - config.height / 2) < 40)] *= 0.9  # the box
        result.append(RGBDFrame(np.round(depth * 1000).astype(np.uint16), intrinsics, pose, depth_scale=0.001))
    return result


def run(config: FusionBenchConfig = FusionBenchConfig()) -> dict[str, float]:
    torch.set_num_threads(1)
    inputs = frames(config)
    box = CropBox((-0.4, -0.4, -0.05), (0.4, 0.4, 0.3))
    rng = np.random.default_rng(0)
    results = {
        "back-projection of both frames": median_seconds(lambda: [frame_points(f) for f in inputs], config.repeats),
        "fusion: back-projection, crop, sampling": median_seconds(
            lambda: fuse_frames(inputs, box, config.num_points, rng), config.repeats),
        **{f"fusion reading every {stride}th pixel ({config.width // stride} x {config.height // stride} per frame)":
           median_seconds(lambda s=stride: fuse_frames(inputs, box, config.num_points, rng, pixel_stride=s),
                          config.repeats) for stride in (4, 8)},
    }
    start = time.perf_counter()
    reading = fuse_frames(inputs, box, config.num_points, rng)
    print(f"\ntwo {config.width} x {config.height} depth frames -> {config.num_points} points "
          f"({reading.num_in_crop} in the box), one thread, median of {config.repeats} "
          f"(one more call: {1000 * (time.perf_counter() - start):.1f} ms)\n")
    print("| step | median ms | target |")
    print("| --- | --- | --- |")
    for name, seconds in results.items():
        print(f"| {name} | {1000 * seconds:.2f} | {'10' if name.startswith('fusion') else '-'} |")
    return results
