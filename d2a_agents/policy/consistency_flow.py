"""Consistency flow matching, FlowPolicy's action expert (``--algo flowpolicy``).

FlowPolicy's conventions (its own, opposite to MeanFlow's here): noise z ~ N(0, I) at t = 0,
data a at t = 1, on the straight path x_t = t a + (1 - t) z. [0, 1] is cut into ``segments``
equal segments; within the segment ending at s the network's velocity v(x_t, t) defines
f(x_t, t) = x_t + (s - t) v(x_t, t), the point it predicts at the segment's end. Training asks
f to agree at two nearby times on the same path: t ~ U[eps, 1], r = min(t + delta, 1), both
measured against t's segment end s; where r reaches s, f_r is the path's exact point x_s. The
loss is |f_t - f_r|^2 + alpha |v_t - v_r|^2, the velocity term only where r lies inside the
segment. Inference is one Euler step from noise: a = z + v(z, 0).

The r branch is the target: here it is computed without gradient (stop-gradient, as
consistency training and MeanFlow's target are); FlowPolicy's released code back-propagates
through both branches and keeps no EMA copy for it. The network is the shared
``net(x, r, t, cond)``, given t for both times.

Example::

    expert = ConsistencyFlow()
    loss, info = expert.loss(net, actions, cond)    # actions normalized to [-1, 1], (B, T, A)
    chunks = expert.sample(net, cond)               # one network evaluation
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from d2a_agents.policy.meanflow import draw, per_sample


@dataclass(frozen=True)
class ConsistencyFlowConfig:
    """FlowPolicy's defaults (its Meta-World and Adroit configs)."""

    eps: float = 1e-2  # t ~ U[eps, 1]
    delta: float = 1e-2  # r = min(t + delta, 1)
    segments: int = 2
    alpha: float = 1e-5  # weight of the velocity-consistency term
    inference_steps: int = 1

    def __post_init__(self) -> None:
        if not 0 <= self.eps < 1 or not 0 < self.delta < 1:
            raise ValueError(f"need 0 <= eps < 1 and 0 < delta < 1, got eps={self.eps}, delta={self.delta}")
        if self.segments < 1 or self.inference_steps < 1:
            raise ValueError("segments and inference_steps must be at least 1")


def segment_ends(t: torch.Tensor, segments: int) -> torch.Tensor:
    """The end of the segment of [0, 1] that holds each t (a segment (s - 1/k, s] ends at s)."""
    return torch.ceil(t * segments).clamp(min=1) / segments


def consistency_flow_loss(
    net: nn.Module, actions: torch.Tensor, noise: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
    config: ConsistencyFlowConfig,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss at given draws: ``actions`` and ``noise`` (B, T, A), times ``t`` (B,)."""
    r = (t + config.delta).clamp(max=1.0)
    end = segment_ends(t, config.segments)
    t_, r_, end_ = (per_sample(x, actions) for x in (t, r, end))
    x_t = t_ * actions + (1 - t_) * noise
    x_r = r_ * actions + (1 - r_) * noise
    v_t = net(x_t, t, t, cond)
    f_t = x_t + (end_ - t_) * v_t
    inside = r < end  # r still in t's segment; else its f is the path's point at the segment end
    with torch.no_grad():
        v_r = net(x_r, r, r, cond)
        f_r = torch.where(per_sample(inside, actions), x_r + (end_ - r_) * v_r, end_ * actions + (1 - end_) * noise)
    f_error = (f_t - f_r).pow(2).flatten(1).mean(dim=1)
    v_error = (v_t - v_r).pow(2).flatten(1).mean(dim=1) * inside
    loss = (f_error + config.alpha * v_error).mean()
    return loss, {"loss": loss.item(), "mse": f_error.mean().item()}


class ConsistencyFlow:
    """Consistency flow matching loss and its few-step Euler sampler over ``net(x, r, t, cond)``."""

    def __init__(self, config: ConsistencyFlowConfig | None = None) -> None:
        self.config = config or ConsistencyFlowConfig()

    def loss(
        self, net: nn.Module, actions: torch.Tensor, cond: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """The loss on normalized action chunks (B, T, A) given conditions (B, C), with its draws."""
        noise = draw("randn", tuple(actions.shape), actions, generator)
        t = self.config.eps + (1 - self.config.eps) * draw("rand", (actions.shape[0],), actions, generator)
        return consistency_flow_loss(net, actions, noise, t, cond, self.config)

    @torch.no_grad()
    def sample(
        self, net: nn.Module, cond: torch.Tensor, generator: torch.Generator | None = None, steps: int | None = None
    ) -> torch.Tensor:
        """Normalized action chunks (B, T, A): ``steps`` Euler steps from noise at t = 0 to t = 1."""
        steps = self.config.inference_steps if steps is None else steps
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        batch = cond.shape[0]
        x = draw("randn", (batch, net.horizon, net.action_dim), cond, generator)
        for k in range(steps):
            t = torch.full((batch,), k / steps, dtype=cond.dtype, device=cond.device)
            x = x + net(x, t, t, cond) / steps
        return x
