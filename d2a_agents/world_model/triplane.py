"""The triplane world model: current occupancy + past actions -> occupancy H steps ahead.

Pipeline (paper, section III-B): voxel grid V_t -> Conv3d encoder -> feature volume
C x X x Y x Z, modulated by the action history (FiLM, zero-initialised so training starts
from "nothing moves") -> axis-wise pooling (mean or max) to three planes P_xy (X x Y),
P_xz (X x Z), P_yz (Y x Z) -> a few dilated 2D convolutions per plane -> for a query point p,
f_p = P_xy(x, y) + P_xz(x, z) + P_yz(y, z) by bilinear interpolation (eq. 1-2) ->
MLP on [f_p, PE(p), V_t(p)] -> occupancy logit of p at t + H (eq. 3).

V_t(p), the current occupancy at the query, is an addition to eq. 3 (``occupancy_skip``):
with it "nothing moves" is one weight away, so the features only have to encode change.

Ablations (Table II): ``xy`` keeps only P_xy; ``volume`` samples the 3D feature volume
trilinearly instead of planes (3D dilated convolutions in place of the 2D ones).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

FEATURE_MODES = ("triplane", "xy", "volume")
PLANE_POOLINGS = ("mean", "max")
ENCODERS = ("volume-conv", "point-scatter")


@dataclass(frozen=True)
class WorldModelConfig:
    """Every hyperparameter of the world model (defaults: the paper's sizes).

    Attributes:
        resolution: voxel grid (X, Y, Z) over the workspace box; the encoder keeps it, so it
            is also the encoded size (H', W', D') = (128, 128, 32) of the paper.
        channels: feature dimension C (paper: 16).
        feature_mode: ``triplane`` (the method), ``xy`` or ``volume`` (ablations).
        plane_pooling: how the volume collapses onto a plane, ``max`` or ``mean`` over the
            collapsed axis (the paper says "axis-wise pooling" without naming it). A mean over
            32 cells dilutes a gripper two cells thick sixteen-fold; a max keeps it. With 2000
            steps on a 32x32x8 grid, max instead of mean raised the triplane's held-out
            dynamic IoU from 14.9 to 27.9 % on Hammer and from 22.0 to 24.3 % on Assembly.
        horizon: H, how many control steps ahead the model imagines.
        action_history: how many past actions condition the prediction.
        reads_actions: False: the model reads zeros for the past actions, so it imagines from
            the scene alone. A policy that reads its imagination then cannot read through it
            the actions that led there (the expert's in training, its own when acting).
        action_dim: size of one action.
        refine_dilations: dilations of the per-plane (or volume) refinement convolutions;
            they widen the receptive field so that motion over H steps can be represented.
        pe_frequencies: sinusoidal positional-embedding frequencies per axis.
        decoder_hidden, decoder_layers: width and depth of the occupancy MLP.
        occupancy_skip: also feed the current occupancy at the query to the decoder.
        encoder: ``volume-conv`` (the paper: Conv3d over the whole grid, then axis-wise
            pooling) or ``point-scatter``: a per-point MLP over the occupied voxels (FiLM
            from the actions), max-scattered onto the planes, so its cost follows the
            occupied voxels (at most N) rather than the X * Y * Z grid. No volume: it
            serves the ``triplane`` and ``xy`` modes.
    """

    resolution: tuple[int, int, int] = (128, 128, 32)
    channels: int = 16
    feature_mode: str = "triplane"
    plane_pooling: str = "max"
    horizon: int = 4
    action_history: int = 4
    action_dim: int = 4
    refine_dilations: tuple[int, ...] = (1, 2, 4)
    pe_frequencies: int = 6
    decoder_hidden: int = 64
    decoder_layers: int = 3
    occupancy_skip: bool = True
    encoder: str = "volume-conv"
    reads_actions: bool = True

    def __post_init__(self) -> None:
        if self.encoder not in ENCODERS:
            raise ValueError(f"encoder must be one of {ENCODERS}, got {self.encoder!r}")
        if self.encoder == "point-scatter" and self.feature_mode == "volume":
            raise ValueError("the point-scatter encoder builds planes, not a volume: use feature_mode triplane or xy")
        if self.feature_mode not in FEATURE_MODES:
            raise ValueError(f"feature_mode must be one of {FEATURE_MODES}, got {self.feature_mode!r}")
        if self.plane_pooling not in PLANE_POOLINGS:
            raise ValueError(f"plane_pooling must be one of {PLANE_POOLINGS}, got {self.plane_pooling!r}")
        if self.horizon < 1 or self.action_history < 1:
            raise ValueError("horizon and action_history must be >= 1")
        object.__setattr__(self, "resolution", tuple(int(r) for r in self.resolution))
        object.__setattr__(self, "refine_dilations", tuple(int(d) for d in self.refine_dilations))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, raw: dict) -> WorldModelConfig:
        """The config a checkpoint recorded, read as this code reads it: a setting added since
        takes the value older code had (a checkpoint without ``plane_pooling`` pooled by the
        mean; the others' defaults are what older code did). An unknown setting is a TypeError."""
        return cls(**{"plane_pooling": "mean", **raw})


# The CPU preset: the paper's grid and C, with the point-scatter encoder, whose cost follows the
# occupied voxels (a Conv3d over 128x128x32 costs seconds per step on a CPU). `d2a bench wm`
# measures it against the earlier 32x32x8 Conv3d model.
CPU_PRESET = WorldModelConfig(encoder="point-scatter")


def sample_plane(plane: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Bilinear features of a (B, C, Hp, Wp) plane at coordinates in [-1, 1].

    ``u`` indexes the first spatial axis (Hp) and ``v`` the second (Wp), both (B, Q); -1 and
    1 are the outer edges of the plane (``align_corners=False``), so cell i is centred at
    (i + 0.5) / Hp * 2 - 1. Returns (B, Q, C). ``grid_sample`` reads grid[..., 0] along the
    last axis, hence the (v, u) order.
    """
    grid = torch.stack([v, u], dim=-1).unsqueeze(1)  # (B, 1, Q, 2)
    features = F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return features.squeeze(2).transpose(1, 2)


def sample_volume(volume: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
    """Trilinear features of a (B, C, X, Y, Z) volume at (B, Q, 3) coordinates in [-1, 1]."""
    grid = xyz.flip(-1)[:, :, None, None, :]  # grid_sample's 5-D grid is ordered (z, y, x)
    features = F.grid_sample(volume, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return features.reshape(volume.shape[0], volume.shape[1], -1).transpose(1, 2)


def positional_embedding(xyz: torch.Tensor, frequencies: int) -> torch.Tensor:
    """[xyz, sin(2^k pi xyz), cos(2^k pi xyz)] for k < frequencies: (..., 3 + 6 * frequencies)."""
    scales = (2.0 ** torch.arange(frequencies, device=xyz.device, dtype=xyz.dtype)) * math.pi
    angles = (xyz[..., None] * scales).flatten(-2)
    return torch.cat([xyz, angles.sin(), angles.cos()], dim=-1)


def _refiner(dimensions: int, channels: int, dilations: tuple[int, ...]) -> nn.Sequential:
    conv = nn.Conv2d if dimensions == 2 else nn.Conv3d
    layers: list[nn.Module] = []
    for dilation in dilations:
        layers += [conv(channels, channels, 3, padding=dilation, dilation=dilation)]
        layers += [nn.GroupNorm(4, channels), nn.SiLU()]
    return nn.Sequential(*layers)


class TriplaneWorldModel(nn.Module):
    """Occupancy of the scene H steps ahead from the current grid and the past actions.

    Example:
        >>> model = TriplaneWorldModel(CPU_PRESET)
        >>> logits = model(occupancy, actions, queries)  # (B, X, Y, Z), (B, K, A), (B, Q, 3) in [-1, 1]
        >>> logits.shape
        torch.Size([B, Q])
    """

    def __init__(self, config: WorldModelConfig) -> None:
        super().__init__()
        self.config = config
        c = config.channels
        if config.encoder == "point-scatter":
            self.encoder = nn.Sequential(nn.Linear(3, c), nn.SiLU(), nn.Linear(c, c))
        else:
            self.encoder = nn.Sequential(
                nn.Conv3d(1, c, 3, padding=1), nn.GroupNorm(4, c), nn.SiLU(),
                nn.Conv3d(c, c, 3, padding=1), nn.GroupNorm(4, c), nn.SiLU(),
            )
        self.film = nn.Sequential(
            nn.Linear(config.action_history * config.action_dim, 128), nn.SiLU(), nn.Linear(128, 2 * c)
        )
        nn.init.zeros_(self.film[-1].weight)
        nn.init.zeros_(self.film[-1].bias)
        if config.feature_mode == "volume":
            self.refine = nn.ModuleList([_refiner(3, c, config.refine_dilations)])
        else:
            planes = 3 if config.feature_mode == "triplane" else 1
            self.refine = nn.ModuleList([_refiner(2, c, config.refine_dilations) for _ in range(planes)])
        width = c + 3 + 6 * config.pe_frequencies + int(config.occupancy_skip)
        layers: list[nn.Module] = []
        for _ in range(config.decoder_layers - 1):
            layers += [nn.Linear(width, config.decoder_hidden), nn.SiLU()]
            width = config.decoder_hidden
        layers.append(nn.Linear(width, 1))
        self.decoder = nn.Sequential(*layers)

    def encode(self, occupancy: torch.Tensor, actions: torch.Tensor) -> list[torch.Tensor]:
        """Feature planes (or the volume) of a batch: occupancy (B, X, Y, Z), actions (B, K, A).

        With ``occupancy_skip`` the current occupancy volume (B, 1, X, Y, Z) is appended last.
        """
        grid = occupancy.float().unsqueeze(1)
        skip = [grid] if self.config.occupancy_skip else []
        if not self.config.reads_actions:
            actions = torch.zeros_like(actions)
        gamma, beta = self.film(actions.flatten(1)).chunk(2, dim=-1)
        mode = self.config.feature_mode
        if self.config.encoder == "point-scatter":
            planes = self._scatter_planes(occupancy, gamma, beta)
        else:
            volume = self.encoder(grid)
            volume = volume * (1 + gamma[:, :, None, None, None]) + beta[:, :, None, None, None]
            if mode == "volume":
                return [self.refine[0](volume), *skip]
            planes = [self._pool(volume, 4)]  # xy: (B, C, X, Y)
            if mode == "triplane":
                planes += [self._pool(volume, 3), self._pool(volume, 2)]  # xz: (B, C, X, Z), yz: (B, C, Y, Z)
        return [*(refine(plane) for refine, plane in zip(self.refine, planes, strict=True)), *skip]

    def _scatter_planes(self, occupancy: torch.Tensor, gamma: torch.Tensor, beta: torch.Tensor) -> list[torch.Tensor]:
        """Planes from the occupied voxels: per-voxel features (MLP of the voxel centre in
        [-1, 1], FiLM from the actions, ReLU so that an empty cell's 0 is the floor), max over
        the voxels that share a plane cell. Equal to max-pooling a volume that holds those
        features at the occupied voxels and 0 elsewhere, without building the volume."""
        batch, (nx, ny, nz) = occupancy.shape[0], self.config.resolution
        b, x, y, z = occupancy.nonzero(as_tuple=True)
        resolution = torch.tensor([nx, ny, nz], device=occupancy.device, dtype=torch.float32)
        centres = (torch.stack([x, y, z], dim=-1).float() + 0.5) / resolution * 2.0 - 1.0
        features = torch.relu(self.encoder(centres) * (1 + gamma[b]) + beta[b])  # (M, C)
        layouts = [((x, y), (nx, ny))]
        if self.config.feature_mode == "triplane":
            layouts += [((x, z), (nx, nz)), ((y, z), (ny, nz))]
        channels, planes = features.shape[1], []
        for (u, v), (nu, nv) in layouts:
            cell = (b * nu + u) * nv + v
            plane = features.new_zeros(batch * nu * nv, channels)
            plane = plane.scatter_reduce(0, cell[:, None].expand(-1, channels), features, reduce="amax")
            planes.append(plane.reshape(batch, nu, nv, channels).permute(0, 3, 1, 2))
        return planes

    def _pool(self, volume: torch.Tensor, dim: int) -> torch.Tensor:
        if self.config.plane_pooling == "max":
            return volume.amax(dim=dim)
        return volume.mean(dim=dim)

    def query_features(self, features: list[torch.Tensor], queries: torch.Tensor) -> torch.Tensor:
        """Summed features (B, Q, C) at queries (B, Q, 3) given in [-1, 1] box coordinates."""
        x, y, z = queries.unbind(-1)
        if self.config.feature_mode == "volume":
            return sample_volume(features[0], queries)
        summed = sample_plane(features[0], x, y)
        if self.config.feature_mode == "triplane":
            summed = summed + sample_plane(features[1], x, z) + sample_plane(features[2], y, z)
        return summed

    def decode(self, features: list[torch.Tensor], queries: torch.Tensor) -> torch.Tensor:
        """Occupancy logits (B, Q) at queries (B, Q, 3) in [-1, 1]."""
        inputs = [self.query_features(features, queries), positional_embedding(queries, self.config.pe_frequencies)]
        if self.config.occupancy_skip:
            inputs.append(sample_volume(features[-1], queries))
        return self.decoder(torch.cat(inputs, dim=-1)).squeeze(-1)

    def forward(self, occupancy: torch.Tensor, actions: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
        return self.decode(self.encode(occupancy, actions), queries)

    def voxel_decoder(self, features: list[torch.Tensor]) -> VoxelDecoder:
        """:meth:`decode` at the voxel centres of one encoded scene, faster (see :class:`VoxelDecoder`)."""
        return VoxelDecoder(self, features)


class VoxelDecoder:
    """Occupancy logits at voxel centres of one encoded scene (batch of 1), equal to
    :meth:`TriplaneWorldModel.decode` at those centres, for imagining at every control step.

    At a voxel centre the bilinear plane samples are the plane cells themselves (planes and
    grid share the resolution) and the occupancy skip is the voxel's own value, so the
    decoder's first layer, being linear, splits into per-cell tables computed once per scene:
    W f_p = (W P_xy)[x, y] + (W P_xz)[x, z] + (W P_yz)[y, z], and W PE(p) = sum over the axes
    of W PE(p_a e_a) - 2 W PE(0) (each axis's terms of PE vanish or are constant at 0). A
    query then costs three row gathers and the decoder's remaining layers instead of plane
    sampling, the positional embedding and the widest matrix product. The volume ablation
    keeps the generic path.
    """

    CHUNK = 4096

    @torch.no_grad()
    def __init__(self, model: TriplaneWorldModel, features: list[torch.Tensor]) -> None:
        if features[0].shape[0] != 1:
            raise ValueError(f"a VoxelDecoder decodes one scene, got a batch of {features[0].shape[0]}")
        self.model, self.features = model, features
        config = model.config
        self.resolution = config.resolution
        self.tables: list[tuple[torch.Tensor, tuple[int, int]]] = []
        if config.feature_mode == "volume":
            return
        first, c = model.decoder[0], config.channels
        weight, bias = first.weight, first.bias
        w_features, w_position = weight[:, :c], weight[:, c : c + 3 + 6 * config.pe_frequencies]
        nx, ny, nz = self.resolution
        axes = []
        for axis, n in enumerate(self.resolution):
            coordinate = (torch.arange(n, dtype=weight.dtype, device=weight.device) + 0.5) / n * 2.0 - 1.0
            point = torch.zeros(n, 3, dtype=weight.dtype, device=weight.device)
            point[:, axis] = coordinate
            axes.append(positional_embedding(point, config.pe_frequencies) @ w_position.T)  # (n, hidden)
        origin = positional_embedding(weight.new_zeros(1, 3), config.pe_frequencies) @ w_position.T
        constant = bias - 2.0 * origin[0]

        def projected(plane: torch.Tensor) -> torch.Tensor:  # (1, C, U, V) -> (U * V, hidden), row u * V + v
            return plane[0].reshape(c, -1).T @ w_features.T

        x_term, y_term, z_term = axes
        if config.feature_mode == "triplane":  # the axis terms ride on the two small planes
            xz = projected(features[1]).view(nx, nz, -1).add_(x_term[:, None] + constant).add_(z_term[None, :])
            yz = projected(features[2]).view(ny, nz, -1).add_(y_term[:, None])
            self.tables = [(projected(features[0]), (0, 1)), (xz.view(nx * nz, -1), (0, 2)),
                           (yz.view(ny * nz, -1), (1, 2))]
        else:  # xy: the z term of the positional embedding needs a table of its own
            xy = projected(features[0]).view(nx, ny, -1).add_(x_term[:, None] + constant).add_(y_term[None, :])
            self.tables = [(xy.view(nx * ny, -1), (0, 1)), (z_term, (2,))]
        self.skip_weight = weight[:, -1] if config.occupancy_skip else None
        self.hidden = model.decoder[1:]

    @torch.no_grad()
    def __call__(self, indices: torch.Tensor) -> torch.Tensor:
        """Logits (Q,) at the centres of voxels ``indices`` (Q, 3), integer (x, y, z).

        Decoded in chunks of ``CHUNK`` voxels: the gathered rows and hidden activations of a
        chunk stay in the CPU cache (38k band voxels at 128x128x32: 2.5x faster than at once).
        """
        if len(indices) > self.CHUNK:
            return torch.cat([self(part) for part in indices.split(self.CHUNK)])
        if not self.tables:
            centres = (indices.float() + 0.5) / torch.tensor(self.resolution, dtype=torch.float32) * 2.0 - 1.0
            return self.model.decode(self.features, centres.to(self.features[0].device).unsqueeze(0))[0]
        first = None
        for table, axes in self.tables:
            row = indices[:, axes[0]]
            for axis in axes[1:]:
                row = row * self.resolution[axis] + indices[:, axis]
            gathered = table.index_select(0, row)
            first = gathered if first is None else first.add_(gathered)
        if self.skip_weight is not None:
            occupied = self.features[-1][0, 0][tuple(indices.T)]
            first.addcmul_(occupied[:, None], self.skip_weight[None, :])
        return self.hidden(first).squeeze(-1)
