"""Point-cloud sensor: cameras -> depth -> world-frame points -> fusion -> crop -> FPS.

The sensor knows nothing about Gymnasium or TorchRL: it reads a MuJoCo ``(model, data)``
pair, so the Gymnasium wrapper and the TorchRL transform share one implementation.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import mujoco
import numpy as np

from d2a_envs.camera import backproject, camera_id, camera_intrinsics, camera_pose
from d2a_envs.depth import DEPTH_BACKENDS, DepthBackend, make_depth_backend
from d2a_envs.rgbd import PointCloudReading, crop_and_sample
from d2a_envs.sampling import CropBox


@dataclass(frozen=True)
class PointCloudConfig:
    """Everything that defines a point-cloud observation.

    Attributes:
        cameras: named MuJoCo cameras whose views are fused in the world frame.
        image_size: (height, width) of each depth image in pixels.
        num_points: points per observation after cropping and farthest-point sampling.
        crop_box: workspace box; points outside are dropped before sampling.
        backend: ``raycast`` (no GL, fast on CPU) or ``render`` (OpenGL rasteriser).
        with_rgb: return (N, 6) points with RGB in [0, 1] instead of (N, 3).
        show_sites: draw the scene's visible sites (Meta-World's goal markers) as MuJoCo's
            renderer does by default; ``False`` keeps only physical geoms.
    """

    cameras: tuple[str, ...]
    crop_box: CropBox
    image_size: tuple[int, int] = (128, 128)
    num_points: int = 1024
    backend: str = "raycast"
    with_rgb: bool = False
    show_sites: bool = True

    def __post_init__(self) -> None:
        cameras = (self.cameras,) if isinstance(self.cameras, str) else tuple(self.cameras)
        if not cameras:
            raise ValueError("at least one camera is needed")
        object.__setattr__(self, "cameras", cameras)
        object.__setattr__(self, "crop_box", CropBox.from_any(self.crop_box))
        size = (self.image_size, self.image_size) if isinstance(self.image_size, int) else tuple(self.image_size)
        if len(size) != 2 or min(size) <= 0:
            raise ValueError(f"image_size must be a positive int or (height, width), got {self.image_size}")
        object.__setattr__(self, "image_size", (int(size[0]), int(size[1])))
        if isinstance(self.num_points, bool) or int(self.num_points) != self.num_points or self.num_points <= 0:
            raise ValueError(f"num_points must be a positive integer, got {self.num_points!r}")
        object.__setattr__(self, "num_points", int(self.num_points))
        if self.backend not in DEPTH_BACKENDS:
            raise ValueError(f"unknown depth backend {self.backend!r}; choose one of {DEPTH_BACKENDS}")

    @property
    def point_dim(self) -> int:
        """3 for xyz, 6 for xyz + rgb."""
        return 6 if self.with_rgb else 3

    def updated(self, **changes: object) -> PointCloudConfig:
        """Copy with some fields changed (``None`` values are ignored)."""
        return replace(self, **{k: v for k, v in changes.items() if v is not None})


class PointCloudSensor:
    """Fuses the configured cameras of a MuJoCo scene into one cropped, sampled cloud.

    Example:
        >>> sensor = PointCloudSensor(config)
        >>> reading = sensor.read(model, data, np.random.default_rng(0))
        >>> reading.points.shape
        (1024, 3)
    """

    def __init__(self, config: PointCloudConfig) -> None:
        self.config = config
        height, width = config.image_size
        self._backend: DepthBackend = make_depth_backend(config.backend, width, height, config.show_sites)
        self._camera_ids: dict[int, list[int]] = {}

    def validate(self, model: mujoco.MjModel) -> None:
        """Raise a clear ``ValueError`` if a configured camera does not exist in ``model``."""
        self._ids_for(model)

    def _ids_for(self, model: mujoco.MjModel) -> list[int]:
        key = id(model)
        if key not in self._camera_ids:
            self._camera_ids[key] = [camera_id(model, name) for name in self.config.cameras]
        return self._camera_ids[key]

    def fused_points(self, model: mujoco.MjModel, data: mujoco.MjData, only_crop: bool = False) -> np.ndarray:
        """Points the cameras see, world frame, before cropping: (M, 3) or (M, 6).

        With ``only_crop`` the backend may skip pixels that cannot land in the crop box.
        """
        region = self.config.crop_box if only_crop else None
        height, width = self.config.image_size
        clouds = []
        for cam in self._ids_for(model):
            image = self._backend.capture(model, data, cam, self.config.with_rgb, region)
            xyz = backproject(image.depth, camera_intrinsics(model, cam, width, height), camera_pose(data, cam))
            if self.config.with_rgb:
                rgb = image.rgb.reshape(-1, 3)[np.isfinite(image.depth.reshape(-1))]
                xyz = np.concatenate([xyz, rgb], axis=1)
            clouds.append(xyz)
        return np.concatenate(clouds, axis=0)

    def read(self, model: mujoco.MjModel, data: mujoco.MjData, rng: np.random.Generator) -> PointCloudReading:
        """Cropped cloud with exactly ``num_points`` rows (float32).

        Raises ``ValueError`` when no point lies in the crop box: that is a configuration
        error (wrong box or cameras), not something to paper over.
        """
        raw = self.fused_points(model, data, only_crop=True)
        return crop_and_sample(raw, self.config.crop_box, self.config.num_points, rng,
                               f"cameras {self.config.cameras}")  # as real cameras' frames are (d2a_envs.rgbd)

    def close(self) -> None:
        """Release the depth backend (GL context, caches)."""
        self._backend.close()
