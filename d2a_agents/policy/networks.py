"""Networks shared by every action expert: observation encoders and the velocity network.

Encoders (DP3 style, paper section III-C): a per-point MLP 3 -> 64 -> 128 -> 256 with
LayerNorm + ReLU, max-pooled over points and projected to 64 (then LayerNorm, as DP3's
encoder ends), one for the current and one for the imagined cloud; an MLP for the
low-dimensional observation (the robot's ``agent_pos``, or the simulator's full ``state`` for
the privileged reference, which then has no cloud at all); for the 2D Diffusion Policy, a
camera image in place of the cloud (:mod:`d2a_agents.policy.image_encoder`); the last ``n_obs_steps``
observations of each, and the imagined cloud of the latest (the paper's one P_{t+H}), are
concatenated into the condition f_c. Clouds arrive normalized
(per axis to [-1, 1], by the policy's normalizer).

The velocity network u(z, r, t | c) maps a noisy action chunk z (B, T, A), two times r <= t
in [0, 1] and the condition to a chunk of the same shape. Flow models read it as the
average velocity on [r, t] (MeanFlow; r = t gives the instantaneous velocity); the
diffusion baseline calls it with r = t and reads the output as the predicted noise. Where
``drop`` is true, the condition is replaced by a learned null embedding: the unconditional
branch that classifier-free guidance needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from d2a_agents.policy.image_encoder import RESNET18_WIDTHS, ImageEncoder, ImageEncoderConfig
from d2a_envs.wrappers import IMAGE_KEY

POINT_DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}


@dataclass(frozen=True)
class EncoderConfig:
    """Observation encoders (defaults: DP3 widths, 64-d per modality as in the paper)."""

    point_widths: tuple[int, ...] = (64, 128, 256)
    embed_dim: int = 64
    state_hidden: int = 64
    n_obs_steps: int = 2
    use_imagination: bool = True
    use_cloud: bool = True  # False: the low-dimensional observation alone (the privileged-state reference)
    use_image: bool = False  # the camera's colour image (the 2D Diffusion Policy), through a ResNet-18
    image_widths: tuple[int, ...] = RESNET18_WIDTHS  # the ResNet-18's four stage widths
    state_key: str = "agent_pos"  # the low-dimensional observation: "agent_pos" or the full "state"
    project_norm: bool = True  # LayerNorm after the cloud projection (DP3); without it the features can collapse
    # Precision of the per-point MLP, the bulk of a training step: "bfloat16" runs it under
    # autocast (weights, max-pool output and projection stay float32). 1.4x faster on a CPU
    # with native bf16 (AVX512-BF16 / AMX; `d2a bench train`), slower on one without.
    point_dtype: str = "float32"
    # Imagined clouds read, from the latest observation backwards: the paper conditions on one
    # imagined cloud, P_{t+H} (1); n_obs_steps reads every observation's (a cloud encoding each).
    imagined_steps: int = 1
    # Clouds per imagined observation, each encoded apart by the imagined-cloud encoder
    # (d2a-oracle's true futures at several horizons, stacked_horizons); 1: one cloud.
    imagined_clouds: int = 1

    def __post_init__(self) -> None:
        if self.point_dtype not in POINT_DTYPES:
            raise ValueError(f"point_dtype must be one of {tuple(POINT_DTYPES)}, got {self.point_dtype!r}")
        if not 1 <= self.imagined_steps <= self.n_obs_steps:
            raise ValueError(f"imagined_steps must be in 1..n_obs_steps ({self.n_obs_steps}), "
                             f"got {self.imagined_steps}")
        if self.imagined_clouds < 1:
            raise ValueError(f"imagined_clouds must be at least 1, not {self.imagined_clouds}")


@dataclass(frozen=True)
class VelocityNetConfig:
    """The velocity network: an MLP over the flattened chunk, FiLM-conditioned per layer."""

    hidden: int = 256
    layers: int = 4
    time_embed_dim: int = 64
    time_scale: float = 1.0  # times in [0, 1] are multiplied by this before the sinusoids


class PointCloudEncoder(nn.Module):
    """Per-point MLP with LayerNorm + ReLU, max-pool over points, linear projection (+ LayerNorm)."""

    def __init__(
        self, widths: tuple[int, ...], out_dim: int, in_dim: int = 3, project_norm: bool = True,
        point_dtype: str = "float32",
    ) -> None:
        super().__init__()
        self.point_dtype = POINT_DTYPES[point_dtype]
        layers: list[nn.Module] = []
        for width in widths:
            # in place: the per-point activations dominate a training step's memory traffic
            layers += [nn.Linear(in_dim, width), nn.LayerNorm(width), nn.ReLU(inplace=True)]
            in_dim = width
        self.point_mlp = nn.Sequential(*layers)
        projection: list[nn.Module] = [nn.Linear(in_dim, out_dim)] + ([nn.LayerNorm(out_dim)] if project_norm else [])
        self.project = nn.Sequential(*projection)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """(..., N, 3) -> (..., out_dim)."""
        low_precision = self.point_dtype != torch.float32
        with torch.autocast(points.device.type, dtype=self.point_dtype, enabled=low_precision):
            features = self.point_mlp(points[..., :3]).max(dim=-2).values
        return self.project(features.float())


class ObservationEncoder(nn.Module):
    """f_c from the last ``n_obs_steps`` observations: clouds (and imagined clouds) and state.

    Input: a mapping with ``point_cloud`` (B, n_obs, N, 3) when ``use_cloud``, ``image``
    (B, n_obs, H, W, 3) when ``use_image``, the ``state_key`` observation (B, n_obs, D) and, when
    ``use_imagination``, ``imagined_point_cloud`` (B, n_obs, N, 3), or (B, n_obs, K, N, 3)
    with ``imagined_clouds`` K > 1, of which the last ``imagined_steps`` are read.
    """

    def __init__(self, config: EncoderConfig, state_dim: int) -> None:
        super().__init__()
        if config.use_imagination and not config.use_cloud:
            raise ValueError("an encoder that reads the imagined cloud must read the current cloud too")
        self.config = config

        def cloud_encoder() -> PointCloudEncoder:
            return PointCloudEncoder(config.point_widths, config.embed_dim, project_norm=config.project_norm,
                                     point_dtype=config.point_dtype)

        self.cloud = cloud_encoder() if config.use_cloud else None
        self.imagined = cloud_encoder() if config.use_imagination else None
        self.image = ImageEncoder(ImageEncoderConfig(config.image_widths), config.embed_dim) if config.use_image \
            else None
        self.state = nn.Sequential(
            nn.Linear(state_dim, config.state_hidden), nn.ReLU(), nn.Linear(config.state_hidden, config.embed_dim)
        )
        imagined = config.imagined_steps * config.imagined_clouds if config.use_imagination else 0
        per_step = 1 + int(config.use_cloud) + int(config.use_image)
        self.out_dim = (config.n_obs_steps * per_step + imagined) * config.embed_dim

    def forward(self, observation: dict[str, torch.Tensor]) -> torch.Tensor:
        parts = [self.state(observation[self.config.state_key])]
        if self.cloud is not None:
            parts.append(self.cloud(observation["point_cloud"]))
        if self.image is not None:
            parts.append(self.image(observation[IMAGE_KEY]))
        if self.imagined is not None:
            parts.append(self.imagined(observation["imagined_point_cloud"][:, -self.config.imagined_steps:]))
        return torch.cat([part.flatten(1) for part in parts], dim=1)


def time_embedding(t: torch.Tensor, dim: int, scale: float = 1.0) -> torch.Tensor:
    """Sinusoidal embedding (B, dim) of times (B,) in [0, 1], multiplied by ``scale`` first.

    Diffusion uses DDPM's scale (1000: discrete timesteps must be told apart). Flow models
    need scale 1: MeanFlow's target contains d u / d t, which a 1000x scale makes enormous
    (training then does not converge).
    """
    half = dim // 2
    frequencies = torch.exp(-math.log(10000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    angles = scale * t.float()[:, None] * frequencies[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class VelocityNet(nn.Module):
    """u(z, r, t | c): residual MLP over the flattened action chunk, FiLM from [c, emb(t), emb(t - r)]."""

    def __init__(self, config: VelocityNetConfig, horizon: int, action_dim: int, cond_dim: int) -> None:
        super().__init__()
        self.config, self.horizon, self.action_dim = config, horizon, action_dim
        self.null_condition = nn.Parameter(torch.zeros(cond_dim))
        context_dim = cond_dim + 2 * config.time_embed_dim
        self.input = nn.Linear(horizon * action_dim, config.hidden)
        self.blocks = nn.ModuleList(
            nn.Sequential(nn.LayerNorm(config.hidden), nn.Linear(config.hidden, config.hidden), nn.SiLU(),
                          nn.Linear(config.hidden, config.hidden))
            for _ in range(config.layers)
        )
        self.films = nn.ModuleList(nn.Linear(context_dim, 2 * config.hidden) for _ in range(config.layers))
        self.output = nn.Linear(config.hidden, horizon * action_dim)
        nn.init.zeros_(self.output.weight)
        nn.init.zeros_(self.output.bias)

    def forward(
        self, z: torch.Tensor, r: torch.Tensor, t: torch.Tensor, cond: torch.Tensor, drop: torch.Tensor | None = None
    ) -> torch.Tensor:
        """z (B, T, A), r and t (B,), cond (B, C), drop (B,) bool -> (B, T, A)."""
        if drop is not None:
            cond = torch.where(drop[:, None], self.null_condition.expand_as(cond), cond)
        dim, scale = self.config.time_embed_dim, self.config.time_scale
        context = torch.cat([cond, time_embedding(t, dim, scale), time_embedding(t - r, dim, scale)], dim=-1)
        hidden = self.input(z.flatten(1))
        for block, film in zip(self.blocks, self.films, strict=True):
            scale, shift = film(context).chunk(2, dim=-1)
            hidden = hidden + block(hidden) * (1 + scale) + shift
        return self.output(hidden).reshape(-1, self.horizon, self.action_dim)
