"""Consistency Policy's student: a consistency trajectory model distilled from an EDM teacher (``--algo cp``).

The student jumps along the teacher's probability-flow ODE from any noise level t down to any
s <= t (CTM, Kim et al., 2024, as the Consistency Policy uses it):

    G(x_t, t, s) = (s / t) x_t + (1 - s / t) g(x_t, t, s),
    g(x_t, t, s) = c_skip(t) x_t + c_out(t) F(c_in(t) x_t, c_noise(s), c_noise(t)),

with EDM's scalings at t (:mod:`d2a_agents.policy.edm`), so G(x, t, t) = x and g(x, t, t) is a
denoiser. Training draws three levels of the Karras discretization (``bins`` levels from
sigma_max to sigma_min): t, the next level u below it, and s at or below u. The teacher takes
one Heun step from x_t = a + t n to x_u; the trajectory loss asks the student's jump from
(x_t, t) to s to land where its own jump from (x_u, u) does, both carried on to sigma_min by
the student with its parameters held fixed (CTM's comparison in the clean space). The
denoising loss trains g(., t, t) as EDM trains D (log-normal sigma, EDM's weight). One step
at inference: a = G(x, sigma_max, sigma_min) from x ~ N(0, sigma_max^2 I); ``inference_steps``
> 1 chains deterministic jumps down the Karras levels.

Where the Consistency Policy's code differs or is silent: the target branch uses the current
student with gradients stopped (no EMA copy of it); the teacher takes one Heun step per bin;
the loss weights are 1 and 1. The condition is the teacher's: the student starts from the
teacher's observation encoder and keeps it frozen, so teacher and student read the same f_c.

Example::

    student = ConsistencyTrajectory(teacher=teacher_policy.net)
    loss, info = student.loss(net, actions, cond)   # actions normalized to [-1, 1], (B, T, A)
    chunks = student.sample(net, cond)              # one network evaluation
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn
from torch.func import functional_call

from d2a_agents.policy.edm import EDM, EDMConfig, karras_sigmas
from d2a_agents.policy.meanflow import draw, per_sample


@dataclass(frozen=True)
class ConsistencyPolicyConfig:
    """The student's settings (the noise range and data scale are the teacher's EDM's)."""

    bins: int = 40  # levels of the Karras discretization that t, u and s are drawn from
    dsm_weight: float = 1.0  # weight of the denoising loss beside the trajectory loss
    inference_steps: int = 1
    edm: EDMConfig = field(default_factory=EDMConfig)

    def __post_init__(self) -> None:
        if self.bins < 2 or self.inference_steps < 1 or self.dsm_weight < 0:
            raise ValueError("need bins >= 2, inference_steps >= 1 and dsm_weight >= 0")


Network = nn.Module | Callable[..., torch.Tensor]  # net(x, r, t, cond), or the same with parameters held fixed


class ConsistencyTrajectory:
    """The student's jump, its distillation loss against ``teacher`` and its sampler."""

    def __init__(self, config: ConsistencyPolicyConfig | None = None, teacher: Network | None = None) -> None:
        self.config = config or ConsistencyPolicyConfig()
        self.edm = EDM(self.config.edm)
        self.teacher = teacher  # the EDM teacher's network, needed for training only
        edm = self.config.edm
        self.levels = torch.tensor(karras_sigmas(self.config.bins, edm.sigma_min, edm.sigma_max, edm.rho))

    def denoiser(self, net: Network, x: torch.Tensor, t: torch.Tensor, s: torch.Tensor,
                 cond: torch.Tensor) -> torch.Tensor:
        """g(x, t, s): the network's clean-chunk estimate, EDM-scaled at t, told the target level s."""
        return self.edm.denoise(net, x, t, cond, target=s)

    def jump(self, net: Network, x: torch.Tensor, t: torch.Tensor, s: torch.Tensor,
             cond: torch.Tensor) -> torch.Tensor:
        """G(x, t, s): where the trajectory through x at level t is at level s <= t (both (B,))."""
        ratio = per_sample(s / t, x)
        return ratio * x + (1 - ratio) * self.denoiser(net, x, t, s, cond)

    def loss(
        self, net: Network, actions: torch.Tensor, cond: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Trajectory loss + ``dsm_weight`` x denoising loss on normalized chunks (B, T, A)."""
        if self.teacher is None:
            raise ValueError("a consistency student trains against an EDM teacher: pass teacher=")
        batch, bins = actions.shape[0], self.config.bins
        levels = self.levels.to(device=actions.device, dtype=actions.dtype)
        n = (draw("rand", (batch,), actions, generator) * (bins - 1)).long().clamp(max=bins - 2)
        m = n + 1 + (draw("rand", (batch,), actions, generator) * (bins - 1 - n)).long().clamp(max=bins - 2 - n)
        t, u, s = levels[n], levels[n + 1], levels[m]
        sigma_min = torch.full_like(t, levels[-1].item())
        noise = draw("randn", tuple(actions.shape), actions, generator)
        x_t = actions + per_sample(t, actions) * noise
        frozen = {name: value.detach() for name, value in net.named_parameters()}

        def held(*inputs: torch.Tensor) -> torch.Tensor:  # the student with its parameters held fixed
            return functional_call(net, frozen, inputs)

        with torch.no_grad():
            x_u = self.edm.heun_step(self.teacher, x_t, t, u, cond)
            target = self.jump(held, self.jump(held, x_u, u, s, cond), s, sigma_min, cond)
        estimate = self.jump(held, self.jump(net, x_t, t, s, cond), s, sigma_min, cond)
        trajectory = (estimate - target).pow(2).flatten(1).mean(dim=1).mean()

        denoising, info = self.edm.loss(net, actions, cond, generator)  # g(., t, t) is EDM's denoiser
        loss = trajectory + self.config.dsm_weight * denoising
        return loss, {"loss": loss.item(), "trajectory": trajectory.item(), "mse": info["mse"]}

    @torch.no_grad()
    def sample(
        self, net: Network, cond: torch.Tensor, generator: torch.Generator | None = None, steps: int | None = None
    ) -> torch.Tensor:
        """Normalized chunks (B, T, A): ``steps`` jumps from N(0, sigma_max^2 I) down to sigma_min."""
        steps = self.config.inference_steps if steps is None else steps
        if steps < 1:
            raise ValueError(f"steps must be at least 1, got {steps}")
        edm = self.config.edm
        batch = cond.shape[0]
        x = draw("randn", (batch, net.horizon, net.action_dim), cond, generator) * edm.sigma_max
        levels = karras_sigmas(steps + 1, edm.sigma_min, edm.sigma_max, edm.rho)
        for t, s in zip(levels[:-1], levels[1:], strict=True):
            x = self.jump(net, x, torch.full((batch,), t, dtype=x.dtype, device=x.device),
                          torch.full((batch,), s, dtype=x.dtype, device=x.device), cond)
        return x.clamp(-1.0, 1.0) if edm.clip_sample else x
