"""Voxel grids over the workspace box: points to occupancy and voxel centres back to points."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from d2a_envs.sampling import CropBox


@dataclass(frozen=True)
class VoxelGrid:
    """A regular grid of ``resolution`` = (X, Y, Z) voxels spanning ``box``.

    Voxel (i, j, k) covers ``low + [i, i + 1) * size`` along x (likewise y, z); the upper
    box face belongs to the last voxel. Points outside the box are dropped, not clamped.

    Example:
        >>> grid = VoxelGrid(CropBox((0, 0, 0), (1, 1, 1)), (4, 4, 2))
        >>> grid.voxelize(torch.tensor([[0.1, 0.1, 0.1], [2.0, 0, 0]])).nonzero().tolist()
        [[0, 0, 0]]
    """

    box: CropBox
    resolution: tuple[int, int, int]

    def __post_init__(self) -> None:
        if len(self.resolution) != 3 or min(self.resolution) <= 0:
            raise ValueError(f"resolution must be three positive ints, got {self.resolution}")

    @property
    def low(self) -> torch.Tensor:
        return torch.tensor(self.box.low, dtype=torch.float32)

    @property
    def voxel_size(self) -> torch.Tensor:
        return (torch.tensor(self.box.high) - torch.tensor(self.box.low)).float() / torch.tensor(self.resolution)

    def indices(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Integer voxel indices (..., 3) of xyz ``points`` (..., >=3) and a mask of points inside."""
        xyz = points[..., :3].float()
        high = torch.tensor(self.box.high, dtype=torch.float32)
        inside = torch.all((xyz >= self.low) & (xyz <= high), dim=-1)
        idx = torch.floor((xyz - self.low) / self.voxel_size).long()
        idx = torch.minimum(idx, torch.tensor(self.resolution) - 1).clamp_min(0)
        return idx, inside

    def voxelize(self, points: torch.Tensor) -> torch.Tensor:
        """Occupancy (bool) of shape (..., X, Y, Z) of a (..., N, 3) cloud."""
        idx, inside = self.indices(points)
        batch_shape, n_points = points.shape[:-2], points.shape[-2]
        n_clouds, (X, Y, Z) = math.prod(batch_shape), self.resolution
        cloud = torch.arange(n_clouds, device=points.device).repeat_interleave(n_points)
        idx = idx.reshape(-1, 3)
        linear = ((cloud * X + idx[:, 0]) * Y + idx[:, 1]) * Z + idx[:, 2]
        occupancy = torch.zeros(n_clouds * X * Y * Z, dtype=torch.bool, device=points.device)
        occupancy[linear[inside.reshape(-1)]] = True
        return occupancy.reshape(*batch_shape, X, Y, Z)

    def centres(self, indices: torch.Tensor) -> torch.Tensor:
        """World-frame centres (..., 3) of voxel ``indices`` (..., 3)."""
        return self.low.to(indices.device) + (indices.float() + 0.5) * self.voxel_size.to(indices.device)

    def normalized(self, points: torch.Tensor) -> torch.Tensor:
        """xyz mapped to [-1, 1] over the box (the convention of ``grid_sample``, align_corners=False)."""
        low, size = self.low.to(points.device), self.voxel_size.to(points.device) * torch.tensor(self.resolution)
        return (points[..., :3] - low) / size * 2.0 - 1.0

    def occupied_centres(self, occupancy: torch.Tensor) -> torch.Tensor:
        """Centres (M, 3) of the occupied voxels of one (X, Y, Z) grid."""
        return self.centres(occupancy.nonzero())
