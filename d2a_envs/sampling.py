"""Workspace cropping and farthest-point sampling of point clouds."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import fpsample
import numpy as np

# KD-tree height of fpsample's bucket FPS (QuickFPS); 5 suits clouds of 1e3-1e5 points.
_FPS_TREE_HEIGHT = 5


@dataclass(frozen=True)
class CropBox:
    """Axis-aligned workspace box in the world frame, metres; points outside are dropped."""

    low: tuple[float, float, float]
    high: tuple[float, float, float]

    def __post_init__(self) -> None:
        low, high = np.asarray(self.low, dtype=float), np.asarray(self.high, dtype=float)
        if low.shape != (3,) or high.shape != (3,):
            raise ValueError(f"crop box corners must be 3 numbers each, got low={self.low}, high={self.high}")
        if not (np.all(np.isfinite(low)) and np.all(np.isfinite(high))):
            raise ValueError(f"crop box corners must be finite, got low={self.low}, high={self.high}")
        if np.any(high <= low):
            axes = [axis for axis, lo, hi in zip("xyz", low, high, strict=True) if hi <= lo]
            raise ValueError(f"crop box is empty or inverted along {axes}: low={self.low}, high={self.high}")
        object.__setattr__(self, "low", tuple(float(v) for v in low))
        object.__setattr__(self, "high", tuple(float(v) for v in high))

    @classmethod
    def from_any(cls, box: CropBox | Sequence[Sequence[float]]) -> CropBox:
        """Accept a ``CropBox``, a ``((x0, y0, z0), (x1, y1, z1))`` pair or six numbers."""
        if isinstance(box, CropBox):
            return box
        corners = np.asarray(box, dtype=float)
        if corners.size != 6:
            raise ValueError(f"a crop box is two corners of 3 numbers (or 6 numbers), got {box!r}")
        low, high = corners.reshape(2, 3)
        return cls(low=tuple(low), high=tuple(high))

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask of the points (M, >=3) whose xyz lie inside the box (bounds included)."""
        xyz = points[:, :3]
        return np.all((xyz >= self.low) & (xyz <= self.high), axis=1)


def farthest_point_indices(points: np.ndarray, n_samples: int) -> np.ndarray:
    """Indices of ``n_samples`` points chosen by farthest-point sampling on xyz.

    Deterministic: sampling starts from the first point. Uses fpsample's bucket QuickFPS,
    about 5x faster than exact FPS at 1e3-1e4 points; its picks can differ from exact FPS
    when distances tie within a bucket, with the same coverage (tests compare both).
    Requires ``n_samples <= len(points)``.
    """
    if n_samples > len(points):
        raise ValueError(f"cannot pick {n_samples} distinct points out of {len(points)}")
    if n_samples == len(points):
        return np.arange(len(points))
    xyz = np.ascontiguousarray(points[:, :3], dtype=np.float32)
    height = min(_FPS_TREE_HEIGHT, int(np.log2(len(points))))  # fpsample needs 2**h <= points
    return fpsample.bucket_fps_kdline_sampling(xyz, n_samples, h=height, start_idx=0).astype(np.int64)


def sample_to_size(points: np.ndarray, n_points: int, rng: np.random.Generator) -> np.ndarray:
    """Exactly ``n_points`` rows: FPS when there are more, resampling with repeats when fewer.

    Filling repeats real points (never zeros) so that encoders never see fake geometry.
    """
    if len(points) == 0:
        raise ValueError("cannot sample from an empty point cloud")
    if len(points) >= n_points:
        return points[farthest_point_indices(points, n_points)]
    extra = rng.integers(0, len(points), size=n_points - len(points))
    return np.concatenate([points, points[extra]], axis=0)
