"""EDM diffusion (Karras et al., 2022), the teacher of the Consistency Policy (``--algo edm``).

Noise levels sigma replace timesteps: x = a + sigma n with n ~ N(0, I). The network is
preconditioned so that its input and target keep unit scale at every sigma:

    D(x; sigma) = c_skip x + c_out F(c_in x, c_noise),
    c_skip = sd^2 / (sigma^2 + sd^2), c_out = sigma sd / sqrt(sigma^2 + sd^2),
    c_in = 1 / sqrt(sigma^2 + sd^2), c_noise = ln(sigma) / 4,

with sd = ``sigma_data``. Training draws ln sigma ~ N(p_mean, p_std^2) and weighs the squared
error of D by (sigma^2 + sd^2) / (sigma sd)^2, which makes it the plain squared error of F
against its own target. Sampling integrates the probability-flow ODE dx/dsigma = (x - D) / sigma
with Heun's method over the Karras schedule sigma_i = (sigma_max^(1/rho) + i / (N - 1)
(sigma_min^(1/rho) - sigma_max^(1/rho)))^rho, then one Euler step to sigma = 0 (EDM's deterministic
sampler, 2N - 1 network evaluations). Defaults are the Consistency Policy's: sigma 0.02-80,
rho 7, sd 0.5. The network is the shared ``net(x, r, t, cond)`` given c_noise for both times.

Example::

    edm = EDM()
    loss, info = edm.loss(net, actions, cond)   # actions normalized to [-1, 1], (B, T, A)
    chunks = edm.sample(net, cond)              # Heun over the Karras schedule
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from d2a_agents.policy.meanflow import draw, per_sample


@dataclass(frozen=True)
class EDMConfig:
    """Every hyperparameter of EDM (defaults: the Consistency Policy's teacher)."""

    sigma_min: float = 0.02
    sigma_max: float = 80.0
    sigma_data: float = 0.5
    rho: float = 7.0
    p_mean: float = -1.2  # ln sigma ~ N(p_mean, p_std^2) in training
    p_std: float = 1.2
    inference_steps: int = 10  # Heun steps over the schedule
    clip_sample: bool = True  # clip the final chunk to the normalized range [-1, 1]

    def __post_init__(self) -> None:
        if not 0 < self.sigma_min < self.sigma_max or self.sigma_data <= 0 or self.rho <= 0:
            raise ValueError("need 0 < sigma_min < sigma_max, sigma_data > 0 and rho > 0")
        if self.inference_steps < 1:
            raise ValueError(f"inference_steps must be at least 1, got {self.inference_steps}")


def karras_sigmas(steps: int, sigma_min: float, sigma_max: float, rho: float) -> list[float]:
    """The ``steps`` noise levels of the Karras schedule, sigma_max first, sigma_min last."""
    if steps == 1:
        return [sigma_max]
    low, high = sigma_min ** (1 / rho), sigma_max ** (1 / rho)
    return [(high + i / (steps - 1) * (low - high)) ** rho for i in range(steps)]


def network_time(sigma: torch.Tensor) -> torch.Tensor:
    """c_noise = ln(sigma) / 4, the network's time input."""
    return sigma.log() / 4


class EDM:
    """EDM's preconditioned denoiser, loss and Heun sampler over ``net(x, r, t, cond)``."""

    def __init__(self, config: EDMConfig | None = None) -> None:
        self.config = config or EDMConfig()

    def scalings(self, sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(c_skip, c_out, c_in) at noise levels ``sigma``."""
        data = self.config.sigma_data
        norm = (sigma**2 + data**2).sqrt()
        return data**2 / norm**2, sigma * data / norm, 1 / norm

    def denoise(self, net: nn.Module, x: torch.Tensor, sigma: torch.Tensor, cond: torch.Tensor,
                target: torch.Tensor | None = None) -> torch.Tensor:
        """D(x; sigma): the network's estimate of the clean chunk, ``sigma`` (B,). ``target``
        (B,), the level the network is told the estimate is for (its first time input), is
        ``sigma`` for EDM itself; the consistency student passes the level it jumps to."""
        c_skip, c_out, c_in = (per_sample(c, x) for c in self.scalings(sigma))
        return c_skip * x + c_out * net(c_in * x, network_time(sigma if target is None else target),
                                        network_time(sigma), cond)

    def loss(
        self, net: nn.Module, actions: torch.Tensor, cond: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """EDM's weighted denoising loss on normalized chunks (B, T, A), sigma log-normal."""
        batch = actions.shape[0]
        sigma = (self.config.p_mean + self.config.p_std * draw("randn", (batch,), actions, generator)).exp()
        noise = draw("randn", tuple(actions.shape), actions, generator)
        denoised = self.denoise(net, actions + per_sample(sigma, actions) * noise, sigma, cond)
        data = self.config.sigma_data
        weight = per_sample((sigma**2 + data**2) / (sigma * data) ** 2, actions)
        error = (denoised - actions).pow(2)
        loss = (weight * error).mean()
        return loss, {"loss": loss.item(), "mse": error.mean().item()}

    def slope(self, net: nn.Module, x: torch.Tensor, sigma: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        """dx/dsigma of the probability-flow ODE, (x - D(x; sigma)) / sigma, ``sigma`` (B,)."""
        return (x - self.denoise(net, x, sigma, cond)) / per_sample(sigma, x)

    def heun_step(
        self, net: nn.Module, x: torch.Tensor, sigma: torch.Tensor, sigma_next: torch.Tensor, cond: torch.Tensor
    ) -> torch.Tensor:
        """One Heun step of the probability-flow ODE from ``sigma`` to ``sigma_next`` (both (B,), > 0)."""
        step = per_sample(sigma_next - sigma, x)
        slope = self.slope(net, x, sigma, cond)
        euler = x + step * slope
        return x + step * (slope + self.slope(net, euler, sigma_next, cond)) / 2

    def schedule(self, steps: int | None = None) -> list[float]:
        """The sampler's noise levels: the Karras schedule, then 0."""
        steps = self.config.inference_steps if steps is None else steps
        if steps < 1:
            raise ValueError(f"steps must be at least 1, got {steps}")
        return [*karras_sigmas(steps, self.config.sigma_min, self.config.sigma_max, self.config.rho), 0.0]

    @torch.no_grad()
    def sample(
        self, net: nn.Module, cond: torch.Tensor, generator: torch.Generator | None = None, steps: int | None = None
    ) -> torch.Tensor:
        """Normalized action chunks (B, T, A): Heun from N(0, sigma_max^2 I) down the schedule."""
        shape = (cond.shape[0], net.horizon, net.action_dim)
        levels = self.schedule(steps)
        x = draw("randn", shape, cond, generator) * levels[0]
        for sigma, sigma_next in zip(levels[:-1], levels[1:], strict=True):
            level, level_next = (torch.full((shape[0],), value, dtype=x.dtype, device=x.device)
                                 for value in (sigma, sigma_next))
            if sigma_next == 0:  # the last step: Euler to the denoiser's estimate
                x = x - sigma * self.slope(net, x, level, cond)
            else:
                x = self.heun_step(net, x, level, level_next, cond)
        return x.clamp(-1.0, 1.0) if self.config.clip_sample else x
