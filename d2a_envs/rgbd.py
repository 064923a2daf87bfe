"""RGB-D frames from any camera fused into the observation the policies read.

A frame is what a real camera driver gives: a depth image (metres, or raw units with a
scale, e.g. millimetres and 0.001; 0 or non-finite = no reading), optional colour, pinhole
intrinsics (fx, fy, cx, cy in pixels, OpenCV's convention: x right, y down, z forward) and the
camera's pose in the robot's base frame (a 4x4 camera-to-base transform in that convention).
For a camera on the hand the pose is the end-effector pose times the hand-eye transform
(:func:`eye_in_hand_pose`). :func:`fuse_frames` back-projects every frame, crops to the
workspace box and samples exactly N points: the same crop and sampling as the simulated envs'
(:func:`crop_and_sample`), so a policy cannot tell where a cloud came from.

Example::

    frames = [RGBDFrame(depth_mm, CameraIntrinsics(615.0, 615.0, 320.0, 240.0), base_from_kinect, depth_scale=0.001),
              RGBDFrame(wrist_depth, wrist_intrinsics, eye_in_hand_pose(base_from_ee, ee_from_camera))]
    reading = fuse_frames(frames, crop_box, num_points=1024, rng=np.random.default_rng(0))
    observation = {"point_cloud": reading.points, "agent_pos": robot_state}
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from d2a_envs.camera import camera_intrinsics, camera_pose
from d2a_envs.sampling import CropBox, sample_to_size

# MuJoCo's camera axes (x right, y up, looking along -z) to OpenCV's (x right, y down, z forward).
_MUJOCO_TO_OPENCV = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics in pixels, OpenCV's convention (pixel (u, v) centred at integer u, v)."""

    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")


@dataclass(frozen=True)
class RGBDFrame:
    """One camera's depth (H, W), optional colour (H, W, 3) in [0, 255] or [0, 1], its
    intrinsics and its camera-to-base pose (4, 4); ``depth * depth_scale`` is metres."""

    depth: np.ndarray
    intrinsics: CameraIntrinsics
    pose: np.ndarray
    rgb: np.ndarray | None = None
    depth_scale: float = 1.0

    def __post_init__(self) -> None:
        if np.ndim(self.depth) != 2:
            raise ValueError(f"depth must be an (H, W) image, got shape {np.shape(self.depth)}")
        if np.shape(self.pose) != (4, 4):
            raise ValueError(f"pose must be a 4x4 camera-to-base transform, got shape {np.shape(self.pose)}")
        if self.rgb is not None and np.shape(self.rgb) != (*np.shape(self.depth), 3):
            raise ValueError(f"rgb must be (H, W, 3) like the depth {np.shape(self.depth)}, got {np.shape(self.rgb)}")
        if not self.depth_scale > 0:
            raise ValueError(f"depth_scale must be positive, got {self.depth_scale}")


def pose_matrix(rotation: np.ndarray, position: np.ndarray) -> np.ndarray:
    """The 4x4 transform of a rotation (3, 3) and a translation (3,)."""
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation, position
    return matrix


def eye_in_hand_pose(base_from_hand: np.ndarray, hand_from_camera: np.ndarray) -> np.ndarray:
    """Camera-to-base pose of a camera carried by the hand: the hand's pose (from the robot's
    state) times the hand-eye calibration (the camera's fixed pose on the hand)."""
    return np.asarray(base_from_hand, dtype=float) @ np.asarray(hand_from_camera, dtype=float)


@functools.lru_cache(maxsize=16)
def _pixel_rays(intrinsics: CameraIntrinsics, height: int, width: int, stride: int) -> np.ndarray:
    """(x / z, y / z, 1) of every ``stride``-th pixel in both directions, (h, w, 3), read-only."""
    u, v = np.meshgrid(np.arange(0, width, stride), np.arange(0, height, stride))
    rays = np.stack([(u - intrinsics.cx) / intrinsics.fx, (v - intrinsics.cy) / intrinsics.fy, np.ones(u.shape)], -1)
    rays.flags.writeable = False
    return rays


def frame_points(frame: RGBDFrame, with_rgb: bool = False, pixel_stride: int = 1) -> np.ndarray:
    """Base-frame points (M, 3), or (M, 6) with colour in [0, 1], of the pixels with a reading;
    ``pixel_stride`` k reads every k-th pixel in both directions (a decimation filter: k^2 fewer
    points for the sampling that follows)."""
    if pixel_stride < 1:
        raise ValueError(f"pixel_stride must be at least 1, got {pixel_stride}")
    depth = np.asarray(frame.depth)[::pixel_stride, ::pixel_stride].astype(np.float64) * frame.depth_scale
    height, width = np.shape(frame.depth)
    valid = np.isfinite(depth) & (depth > 0)
    camera = _pixel_rays(frame.intrinsics, height, width, pixel_stride)[valid] * depth[valid, None]
    pose = np.asarray(frame.pose, dtype=float)
    points = camera @ pose[:3, :3].T + pose[:3, 3]
    if not with_rgb:
        return points
    if frame.rgb is None:
        raise ValueError("with_rgb needs every frame to carry colour")
    rgb = np.asarray(frame.rgb, dtype=np.float64)[::pixel_stride, ::pixel_stride][valid]
    return np.concatenate([points, rgb / 255.0 if rgb.max(initial=0) > 1.0 else rgb], axis=1)


@dataclass
class PointCloudReading:
    """One observation: exactly ``num_points`` points and how many the crop really held."""

    points: np.ndarray
    num_in_crop: int


def crop_and_sample(points: np.ndarray, crop_box: CropBox, num_points: int, rng: np.random.Generator,
                    source: str = "the cameras") -> PointCloudReading:
    """The points inside the workspace box, sampled to exactly ``num_points`` (float32); a
    ``ValueError`` naming ``source`` when none lies inside (a wrong box or pose, not noise)."""
    cropped = points[crop_box.contains(points)]
    if len(cropped) == 0:
        raise ValueError(f"no point seen by {source} lies inside the crop box low={crop_box.low}, "
                         f"high={crop_box.high}; check the box and the camera poses")
    return PointCloudReading(sample_to_size(cropped, num_points, rng).astype(np.float32), len(cropped))


def fuse_frames(
    frames: Sequence[RGBDFrame], crop_box: CropBox, num_points: int, rng: np.random.Generator,
    with_rgb: bool = False, pixel_stride: int = 1,
) -> PointCloudReading:
    """Every frame back-projected into the base frame (every ``pixel_stride``-th pixel), fused,
    cropped and sampled to N points."""
    if not frames:
        raise ValueError("fuse_frames needs at least one frame")
    points = np.concatenate([frame_points(frame, with_rgb, pixel_stride) for frame in frames], axis=0)
    return crop_and_sample(points, CropBox.from_any(crop_box), num_points, rng, f"{len(frames)} frame(s)")


def mujoco_frame(
    model: mujoco.MjModel, data: mujoco.MjData, cam_id: int, depth: np.ndarray, rgb: np.ndarray | None = None,
) -> RGBDFrame:
    """A MuJoCo camera's depth image (rows top-down) as a frame in OpenCV's convention, world
    frame as the base: how simulated cameras enter the real-camera path."""
    height, width = depth.shape
    focal = camera_intrinsics(model, cam_id, width, height).focal
    # MuJoCo samples pixel centres at (u + 0.5 - W / 2) / f: OpenCV's cx = W / 2 - 0.5.
    intrinsics = CameraIntrinsics(focal, focal, width / 2.0 - 0.5, height / 2.0 - 0.5)
    pose = camera_pose(data, cam_id)
    return RGBDFrame(np.where(np.isfinite(depth), depth, 0.0), intrinsics,
                     pose_matrix(pose.rotation @ _MUJOCO_TO_OPENCV, pose.position), rgb)
