"""Pinhole geometry of MuJoCo cameras: pixel rays, poses and depth-to-point back-projection.

Conventions (MuJoCo/OpenGL): a camera looks along its local -z axis, +x points right and
+y up in the image. ``data.cam_xmat`` holds the camera axes as the columns of a world-frame
rotation. Image row 0 is the top of the picture (MuJoCo's renderer output flipped to the
usual image order). The pixel (row v, column u) is sampled through its centre,
(u + 0.5, v + 0.5), which is what OpenGL rasterisation does; sampling through the corner
instead shifts every point by half a pixel (about 1 cm at 1 m with 128 px).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import mujoco
import numpy as np


@dataclass(frozen=True)
class PinholeIntrinsics:
    """Intrinsics of a square-pixel pinhole camera with the principal point at the centre."""

    width: int
    height: int
    focal: float

    @classmethod
    def from_fovy(cls, fovy_degrees: float, width: int, height: int) -> PinholeIntrinsics:
        """MuJoCo's ``fovy`` is the vertical field of view: f = H / (2 tan(fovy / 2))."""
        focal = height / (2.0 * math.tan(math.radians(fovy_degrees) / 2.0))
        return cls(width=width, height=height, focal=focal)

    def ray_directions(self) -> np.ndarray:
        """Camera-frame direction of every pixel centre, row-major, shape (H * W, 3).

        Each direction has z = -1, so the distance along it is the depth (the z-buffer
        distance along the optical axis) rather than the Euclidean range. The array is
        cached and read-only.
        """
        return _ray_directions(self.width, self.height, self.focal)


@functools.lru_cache(maxsize=64)
def _ray_directions(width: int, height: int, focal: float) -> np.ndarray:
    u = (np.arange(width) + 0.5 - width / 2.0) / focal
    v = (np.arange(height) + 0.5 - height / 2.0) / focal
    uu, vv = np.meshgrid(u, v)
    directions = np.stack([uu, -vv, -np.ones_like(uu)], axis=-1).reshape(-1, 3)
    directions.flags.writeable = False
    return directions


@dataclass(frozen=True)
class CameraPose:
    """World-frame position and rotation (columns = camera x, y, z axes) of a camera."""

    position: np.ndarray
    rotation: np.ndarray


def camera_id(model: mujoco.MjModel, name: str) -> int:
    """Id of the named camera, or a ``ValueError`` that lists the cameras the model has."""
    cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
    if cam_id < 0:
        raise ValueError(f"unknown camera {name!r}; this model has cameras {camera_names(model)}")
    return cam_id


def camera_names(model: mujoco.MjModel) -> list[str]:
    """Names of all cameras of a model, in id order."""
    return [model.camera(i).name for i in range(model.ncam)]


def camera_intrinsics(model: mujoco.MjModel, cam_id: int, width: int, height: int) -> PinholeIntrinsics:
    """Intrinsics of camera ``cam_id`` rendered at ``width`` x ``height`` pixels."""
    return PinholeIntrinsics.from_fovy(float(model.cam_fovy[cam_id]), width, height)


def camera_pose(data: mujoco.MjData, cam_id: int) -> CameraPose:
    """Current world pose of camera ``cam_id`` (valid after ``mj_forward``/``mj_step``)."""
    return CameraPose(
        position=data.cam_xpos[cam_id].copy(),
        rotation=data.cam_xmat[cam_id].reshape(3, 3).copy(),
    )


def backproject(depth: np.ndarray, intrinsics: PinholeIntrinsics, pose: CameraPose) -> np.ndarray:
    """World-frame points of the pixels with finite depth, shape (M, 3), row-major order."""
    directions = intrinsics.ray_directions()
    flat = depth.reshape(-1)
    valid = np.isfinite(flat)
    points_camera = directions[valid] * flat[valid, None]
    return points_camera @ pose.rotation.T + pose.position
