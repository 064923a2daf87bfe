"""DP3-style diffusion baseline: DDPM training, deterministic DDIM sampling.

Same interface as the MeanFlow expert (``loss`` and ``sample`` over the shared network), so
the baseline runs through the same data and evaluation path. The network is called as
``net(x_t, t, t, cond)`` with t = timestep / num_train_timesteps in [0, 1]; its output is
read as the predicted noise (``prediction_type="epsilon"``) or as the clean chunk
(``"sample"``, what the official DP3 config uses).

Schedule and sampler follow what DP3 configures in diffusers, written out here: the
"squaredcos_cap_v2" betas (improved DDPM cosine schedule, betas capped at 0.999), DDIM with
"leading" spacing (timesteps k * T // steps, largest first), the predicted clean chunk
clipped to [-1, 1] (actions are normalised), and alpha_bar = 1 after the last step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

SCHEDULES = ("squaredcos_cap_v2",)
PREDICTIONS = ("epsilon", "sample")


@dataclass(frozen=True)
class DiffusionConfig:
    """Every hyperparameter of the diffusion baseline (defaults: DP3)."""

    num_train_timesteps: int = 100
    beta_schedule: str = "squaredcos_cap_v2"
    cosine_offset: float = 0.008  # s in alpha_bar(t) = cos^2(((t + s) / (1 + s)) * pi / 2)
    max_beta: float = 0.999  # the cap that keeps the last beta below 1
    prediction_type: str = "epsilon"
    inference_steps: int = 10
    clip_sample: bool = True
    clip_range: float = 1.0
    eta: float = 0.0  # 0: deterministic DDIM; 1: DDPM posterior variance

    def __post_init__(self) -> None:
        if self.beta_schedule not in SCHEDULES:
            raise ValueError(f"beta_schedule must be one of {SCHEDULES}, got {self.beta_schedule!r}")
        if self.prediction_type not in PREDICTIONS:
            raise ValueError(f"prediction_type must be one of {PREDICTIONS}, got {self.prediction_type!r}")
        if not 1 <= self.inference_steps <= self.num_train_timesteps:
            raise ValueError("inference_steps must lie in [1, num_train_timesteps]")


def cosine_betas(num_steps: int, offset: float, max_beta: float) -> torch.Tensor:
    """Betas (float64) of the squared-cosine schedule: 1 - alpha_bar((i+1)/T) / alpha_bar(i/T), capped."""

    def alpha_bar(t: float) -> float:
        return math.cos((t + offset) / (1 + offset) * math.pi / 2) ** 2

    return torch.tensor(
        [min(1 - alpha_bar((i + 1) / num_steps) / alpha_bar(i / num_steps), max_beta) for i in range(num_steps)],
        dtype=torch.float64,
    )


def _randn(shape: tuple[int, ...], like: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """Standard normal noise drawn on the generator's device (reproducible), moved to ``like``'s."""
    device = generator.device if generator is not None else like.device
    return torch.randn(shape, generator=generator, device=device, dtype=like.dtype).to(like.device)


class Diffusion:
    """DDPM loss and DDIM sampler over the shared network ``net(z, r, t, cond) -> (B, T, A)``."""

    def __init__(self, config: DiffusionConfig | None = None) -> None:
        self.config = config or DiffusionConfig()
        betas = cosine_betas(self.config.num_train_timesteps, self.config.cosine_offset, self.config.max_beta)
        self.alphas_cumprod = torch.cumprod(1 - betas, dim=0)

    def alpha_bar(self, timesteps: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """alpha_bar at integer timesteps (B,), broadcastable against ``like``; timestep -1 (clean) gives 1."""
        padded = torch.cat([torch.ones(1, dtype=torch.float64), self.alphas_cumprod])
        values = padded[timesteps.cpu().long() + 1].to(device=like.device, dtype=like.dtype)
        return values.reshape(-1, *([1] * (like.dim() - 1)))

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """q(x_t | x_0) in closed form: sqrt(abar_t) x0 + sqrt(1 - abar_t) noise."""
        abar = self.alpha_bar(timesteps, x0)
        return abar.sqrt() * x0 + (1 - abar).sqrt() * noise

    def inference_timesteps(self, steps: int | None = None) -> list[int]:
        """The DDIM timesteps, largest first: k * (T // steps) for k = steps - 1, ..., 0."""
        steps = self.config.inference_steps if steps is None else steps
        if not 1 <= steps <= self.config.num_train_timesteps:
            raise ValueError(f"steps must lie in [1, {self.config.num_train_timesteps}], got {steps}")
        ratio = self.config.num_train_timesteps // steps
        return [k * ratio for k in reversed(range(steps))]

    def _network_times(self, timesteps: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """Integer timesteps -> the network's time input in [0, 1]."""
        return timesteps.to(device=like.device, dtype=like.dtype) / self.config.num_train_timesteps

    def loss(
        self, net: nn.Module, actions: torch.Tensor, cond: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """DDPM training loss: uniform timesteps, closed-form noising, MSE on the predicted noise (or chunk)."""
        batch = actions.shape[0]
        device = generator.device if generator is not None else actions.device
        timesteps = torch.randint(self.config.num_train_timesteps, (batch,), generator=generator, device=device)
        noise = _randn(tuple(actions.shape), actions, generator)
        noisy = self.add_noise(actions, noise, timesteps)
        t = self._network_times(timesteps, actions)
        prediction = net(noisy, t, t, cond)
        target = noise if self.config.prediction_type == "epsilon" else actions
        loss = torch.mean((prediction - target) ** 2)
        return loss, {"mse": loss.item()}

    def ddim_step(
        self,
        prediction: torch.Tensor,
        timestep: int,
        prev_timestep: int,
        sample: torch.Tensor,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """One DDIM update x_t -> x_prev from the network's prediction (prev_timestep -1: the clean end).

        The predicted clean chunk is clipped when ``clip_sample``; the noise estimate is the
        unclipped one (diffusers' default), so eta = 0 is exactly the textbook update when
        nothing needs clipping.
        """
        batch = sample.shape[0]
        abar = self.alpha_bar(torch.full((batch,), timestep), sample)
        abar_prev = self.alpha_bar(torch.full((batch,), prev_timestep), sample)
        if self.config.prediction_type == "epsilon":
            eps = prediction
            x0 = (sample - (1 - abar).sqrt() * eps) / abar.sqrt()
        else:
            x0 = prediction
            eps = (sample - abar.sqrt() * x0) / (1 - abar).sqrt()
        if self.config.clip_sample:
            x0 = x0.clamp(-self.config.clip_range, self.config.clip_range)
        sigma = self.config.eta * ((1 - abar_prev) / (1 - abar) * (1 - abar / abar_prev)).sqrt()
        mean = abar_prev.sqrt() * x0 + (1 - abar_prev - sigma**2).clamp(min=0).sqrt() * eps
        if self.config.eta == 0:
            return mean
        return mean + sigma * _randn(tuple(sample.shape), sample, generator)

    @torch.no_grad()
    def sample(
        self, net: nn.Module, cond: torch.Tensor, generator: torch.Generator | None = None, steps: int | None = None
    ) -> torch.Tensor:
        """Action chunks (B, T, A) by DDIM from pure noise: one network evaluation per inference step."""
        shape = (cond.shape[0], net.horizon, net.action_dim)
        x = _randn(shape, cond, generator)
        timesteps = self.inference_timesteps(steps)
        for timestep, prev_timestep in zip(timesteps, [*timesteps[1:], -1], strict=True):
            t = self._network_times(torch.full((shape[0],), timestep), cond)
            x = self.ddim_step(net(x, t, t, cond), timestep, prev_timestep, x, generator)
        return x
