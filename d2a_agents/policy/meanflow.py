"""MeanFlow action expert with adaptive classifier-free guidance (paper section III-C, eq. 5-8).

Conventions (DESIGN section 4): data A_0 (normalized action chunks), noise A_1 ~ N(0, I),
z_t = (1 - t) A_0 + t A_1, instantaneous velocity v = A_1 - A_0. The network
``net(z, r, t, cond, drop)`` predicts the average velocity u on [r, t], so one step from noise
is A_0 = A_1 - u(A_1, 0, 1 | c).

Training target (eq. 5, the MeanFlow identity): u_tgt = v - (t - r) (v . grad_z u + d_t u), the
total derivative taken with ``torch.func.jvp`` along the tangents (v, 0, 1) of (z, r, t), and
stop-gradient on the target. d_t u enters the target directly, so the network must be smooth
in t: a sinusoidal time embedding with frequencies up to 1000 / unit (DDPM's scaling) makes the
target blow up (measured on a 2-D toy: per-element error ~1e2 instead of ~0.7, no convergence).

Adaptive CFG (eq. 6-7) enters as the TRAINING target, MeanFlow style: for the conditional
samples of a batch, the velocity in eq. 5 (both the target and the JVP tangent) is replaced by
v_cfg = w v + (1 - w) u(z_t, t, t | null), with w the gate of eq. 7 on a cosine similarity rho.
Eq. 8 trains u^cfg directly, so the guidance is folded into the network and inference stays at
ONE conditional network evaluation per action chunk, the paper's claim; a sampling-time CFG
would need a second, unconditional evaluation. The samples whose condition is dropped (the
unconditional branch, ``drop_probability`` of the batch) keep v as their target, so the null
branch learns the unconditional velocity. With ``cfg_enabled`` false nothing is dropped and
the null branch is never evaluated (plain MeanFlow, the MP1 / "w/o A-CFG" variants).

The paper's rho is the cosine between v_t(. | c) and u(z_t, t, t | null), and v_t(. | c) reads
two ways. ``cfg_similarity="velocity"`` takes the sampled conditional velocity A_1 - A_0, as
MeanFlow's own CFG target does; ``"prediction"`` (the default) takes the network's conditional
prediction u(z_t, t, t | c). The direction of eq. 7 is the paper's either way: w = 0
(target = the unconditional prediction) where they disagree, w = 1 (plain v) where they
agree. As w lies in [0, 1], eq. 6 only interpolates towards the unconditional field; it
never amplifies the condition as MeanFlow's w > 1 does. Because the "velocity" rho depends on
the sample's own noise, the gate favours the samples whose v already agrees with the
unconditional mean and biases the learned field, even when the condition carries no
information (2-D toy with a constant condition, tests/test_meanflow.py: one-step energy
distance 0.04-0.05, samples pulled towards the centre, against 0.008-0.014 without CFG).
The "prediction" rho is a function of (z_t, c) alone, with no such bias (0.006-0.012 on the
toy), for one more gradient-free evaluation per training step.

The "velocity" gate also acts where it hurts most: near the data. On Hammer (a trained policy,
thresholds (-1, 0)), cos(v, u_null) falls below 0 for 27 % of the samples with t < 0.1 and
18 % of those with t in [0.1, 0.3), where the target moves by a mean squared 0.50 and 0.21
per normalized action element (0.86 and 0.43 on the gripper), against under 1 % of the
samples and 0.001 for t > 0.6; the batch-mean w stays at 0.99 and hides it. The prediction
gate moves the target by 0.02 at t < 0.1. Success on Hammer (mp1 plus the CFG target, 4000
steps of the cpu preset, 50 episodes per seed): "velocity" 0 / 0 / 0 %, "prediction"
6 / 12 / 0 %, condition dropout alone (w = 1) 20 / 22 %, mp1 18 / 20 / 24 %. Any pull
towards the unconditional field costs success at this budget; the prediction gate costs least.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torch.func import jvp

CFG_SIMILARITIES = ("velocity", "prediction")
CFG_GUIDANCES = ("interpolate", "amplify")
NETWORK_OUTPUTS = ("velocity", "action")


@dataclass(frozen=True)
class MeanFlowConfig:
    """Every hyperparameter of the MeanFlow expert.

    (r, t): two logit-normal draws sigmoid(N(time_mean, time_std)), t the larger, r the
    smaller; r = t (plain flow matching) on a random ``flow_ratio_equal`` fraction of the batch
    (MeanFlow uses 0.75, MP1 0.5). Loss weight 1 / (||delta||^2 + adaptive_eps)^adaptive_power
    (MeanFlow's adaptive loss; p = 0 gives the plain squared error).

    CFG thresholds, in cosine-similarity units: w = 0 for rho <= tau_l, 1 for rho >= tau_h,
    linear between (eq. 7; the paper gives no values). The defaults (-1, 0), the policy's too
    (``PolicyConfig.cfg_thresholds``, where the Hammer runs that chose them are noted), keep
    the conditional velocity wherever the two predictions share a direction (rho >= 0) and
    blend towards the unconditional one only as they turn opposite. ``tau_l = 0`` instead
    sets w = 0 for every rho <= 0, which is where an untrained null branch starts (at a
    zero-initialised output layer u_null = 0, so rho = 0): the conditional branch then first
    learns the unconditional field. ``cfg_similarity``: "prediction" (rho =
    cos(u_cond, u_null)) or "velocity" (rho = cos(v, u_null)); see the module docstring.
    """

    time_mean: float = -0.4
    time_std: float = 1.0
    flow_ratio_equal: float = 0.5
    adaptive_power: float = 1.0
    adaptive_eps: float = 1e-3
    drop_probability: float = 0.1
    cfg_enabled: bool = True
    tau_l: float = -1.0
    tau_h: float = 0.0
    cfg_similarity: str = "prediction"
    # How the gate w of eq. 7 shapes the target. "interpolate" (the paper's eq. 6 as written):
    # v_cfg = w v + (1 - w) u_null, w in [0, 1], only ever towards the unconditional field.
    # "amplify" (guidance as MeanFlow and MP1 use it, gated): v_cfg = s v + (1 - s) u_null with
    # s = 1 + cfg_scale * w, i.e. away from the unconditional field by up to cfg_scale where the
    # two predictions agree (w = 1) and plain v where they disagree (w = 0).
    cfg_guidance: str = "interpolate"
    cfg_scale: float = 1.0
    inference_steps: int = 1
    # What the network outputs: "velocity" (u itself, as MeanFlow and MP1 train it) or "action"
    # (the clean chunk x, read as u = (z - x) / max(t, min_time); see ActionOutput).
    network_output: str = "velocity"
    min_time: float = 0.05

    def __post_init__(self) -> None:
        if self.time_std <= 0:
            raise ValueError("time_std must be positive")
        if not 0.0 <= self.flow_ratio_equal <= 1.0:
            raise ValueError("flow_ratio_equal must lie in [0, 1]")
        if self.adaptive_power < 0 or self.adaptive_eps <= 0:
            raise ValueError("adaptive_power must be >= 0 and adaptive_eps > 0")
        if not 0.0 <= self.drop_probability < 1.0:
            raise ValueError("drop_probability must lie in [0, 1)")
        if not -1.0 <= self.tau_l < self.tau_h <= 1.0:
            raise ValueError("CFG thresholds need -1 <= tau_l < tau_h <= 1")
        if self.cfg_similarity not in CFG_SIMILARITIES:
            raise ValueError(f"cfg_similarity must be one of {CFG_SIMILARITIES}, got {self.cfg_similarity!r}")
        if self.cfg_guidance not in CFG_GUIDANCES:
            raise ValueError(f"cfg_guidance must be one of {CFG_GUIDANCES}, got {self.cfg_guidance!r}")
        if self.cfg_scale < 0:
            raise ValueError("cfg_scale must be >= 0")
        if self.inference_steps < 1:
            raise ValueError("inference_steps must be >= 1")
        if self.network_output not in NETWORK_OUTPUTS:
            raise ValueError(f"network_output must be one of {NETWORK_OUTPUTS}, got {self.network_output!r}")
        if not 0 < self.min_time <= 1:
            raise ValueError(f"min_time must lie in (0, 1], got {self.min_time}")


def cfg_weight(rho: torch.Tensor, tau_l: float, tau_h: float) -> torch.Tensor:
    """Eq. 7: the guidance gate w(rho): 0 for rho <= tau_l, (rho - tau_l) / (tau_h - tau_l)
    between, 1 for rho >= tau_h."""
    return ((rho - tau_l) / (tau_h - tau_l)).clamp(0.0, 1.0)


def per_sample(x: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Reshape a per-sample (B,) tensor to broadcast against a (B, ...) tensor."""
    return x.reshape(-1, *([1] * (like.dim() - 1)))


def draw(
    kind: str, shape: tuple[int, ...], like: torch.Tensor, generator: torch.Generator | None
) -> torch.Tensor:
    """Uniform ("rand") or normal ("randn") draws on the generator's device (reproducible), moved to ``like``'s."""
    device = generator.device if generator is not None else like.device
    draw = torch.rand if kind == "rand" else torch.randn
    return draw(shape, generator=generator, device=device, dtype=like.dtype).to(like.device)


def meanflow_target(
    net: Callable[..., torch.Tensor],
    z: torch.Tensor,
    r: torch.Tensor,
    t: torch.Tensor,
    v: torch.Tensor,
    cond: torch.Tensor,
    drop: torch.Tensor | None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The prediction u(z, r, t | c) (with gradient) and the eq. 5 target (detached).

    The total derivative du/dt = v . grad_z u + d_t u is the JVP of (z, r, t) -> u along
    (v, 0, 1); the JVP's primal output is the prediction, so one forward pass serves both.
    """

    def average_velocity(z_: torch.Tensor, r_: torch.Tensor, t_: torch.Tensor) -> torch.Tensor:
        return net(z_, r_, t_, cond, drop)

    u, du_dt = jvp(average_velocity, (z, r, t), (v, torch.zeros_like(r), torch.ones_like(t)))
    target = v - per_sample(t - r, v) * du_dt
    return u, target.detach()


class ActionOutput:
    """A network that outputs the clean action chunk x, called as the average velocity it
    implies: u(z, r, t) = (z - x) / max(t, min_time).

    Where the demonstrated action is one function of the condition, the flow runs straight
    from each noise to that action, u = A_1 - A_0 = (z_t - A_0) / t on every [r, t], so the
    network's answer is the action itself, whatever z, r and t are; read as a velocity it must
    instead carry the noise z through to its output, which a network narrower than the chunk
    hardly does. Below ``min_time`` the division is capped, as x-prediction flow models cap it
    (the answer there is no longer constant in z, but any u stays reachable).
    """

    def __init__(self, net: nn.Module, min_time: float) -> None:
        self.net, self.min_time = net, min_time

    def __call__(self, z: torch.Tensor, r: torch.Tensor, t: torch.Tensor, cond: torch.Tensor,
                 drop: torch.Tensor | None = None) -> torch.Tensor:
        return (z - self.net(z, r, t, cond, drop)) / per_sample(t.clamp_min(self.min_time), z)


class MeanFlow:
    """MeanFlow loss (with adaptive CFG in the target) and few-step sampler over ``net(z, r, t, cond, drop)``."""

    def __init__(self, config: MeanFlowConfig | None = None) -> None:
        self.config = config or MeanFlowConfig()

    def velocity_field(self, net: nn.Module) -> Callable[..., torch.Tensor]:
        """``net`` as the average velocity u(z, r, t, cond, drop), by ``config.network_output``."""
        return net if self.config.network_output == "velocity" else ActionOutput(net, self.config.min_time)

    def sample_times(
        self, batch: int, like: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(r, t), each (B,): logit-normal pair sorted so r <= t, r = t on ``flow_ratio_equal`` of the batch."""
        c = self.config
        times = torch.sigmoid(c.time_mean + c.time_std * draw("randn", (2, batch), like, generator))
        r, t = times.min(dim=0).values, times.max(dim=0).values
        equal = draw("rand", (batch,), like, generator) < c.flow_ratio_equal
        return torch.where(equal, t, r), t

    def guided_velocity(
        self, net: nn.Module, z: torch.Tensor, t: torch.Tensor, v: torch.Tensor, cond: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Eq. 6-7: v_cfg = w v + (1 - w) u(z, t, t | null), w = cfg_weight(rho); returns (v_cfg, w, rho).
        With ``cfg_guidance="amplify"`` the mixing weight is 1 + cfg_scale * w instead of w.

        rho = cos(v, u_null) (the paper) or cos(u_cond, u_null) (``cfg_similarity``). The
        predictions are target ingredients only, so they are taken without gradient; the
        conditional one shares the null one's forward pass (one batch of 2B).
        """
        batch = z.shape[0]
        net = self.velocity_field(net)
        with torch.no_grad():
            if self.config.cfg_similarity == "velocity":
                u_null = net(z, t, t, cond, torch.ones(batch, dtype=torch.bool, device=z.device))
                reference = v
            else:
                drop = torch.arange(2 * batch, device=z.device) < batch
                both = net(torch.cat([z, z]), torch.cat([t, t]), torch.cat([t, t]), torch.cat([cond, cond]), drop)
                u_null, reference = both[:batch], both[batch:]
        rho = F.cosine_similarity(reference.flatten(1), u_null.flatten(1), dim=1)
        w = cfg_weight(rho, self.config.tau_l, self.config.tau_h)
        mix = 1 + self.config.cfg_scale * w if self.config.cfg_guidance == "amplify" else w
        return per_sample(mix, v) * v + per_sample(1 - mix, v) * u_null, w, rho

    def loss(
        self, net: nn.Module, actions: torch.Tensor, cond: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Adaptively weighted MeanFlow loss on normalized action chunks (B, T, A) given conditions (B, C).

        Returns the scalar loss and floats for logging: ``loss``, ``mse`` (unweighted, per
        element) and, with CFG, ``drop_fraction``, ``cfg_weight``, ``cfg_rho`` and ``cfg_active``
        (over the conditional samples: the means of w and rho, and the fraction whose target
        the gate changes, w < 1).
        """
        c = self.config
        batch = actions.shape[0]
        noise = draw("randn", tuple(actions.shape), actions, generator)
        r, t = self.sample_times(batch, actions, generator)
        z = (1 - per_sample(t, actions)) * actions + per_sample(t, actions) * noise
        v = noise - actions
        info: dict[str, float] = {}
        drop = None
        if c.cfg_enabled:
            drop = draw("rand", (batch,), actions, generator) < c.drop_probability
            v_cfg, w, rho = self.guided_velocity(net, z, t, v, cond)
            v = torch.where(per_sample(drop, v), v, v_cfg)
            kept = ~drop
            info["drop_fraction"] = drop.float().mean().item()
            for key, value in (("cfg_weight", w), ("cfg_rho", rho), ("cfg_active", (w < 1).float())):
                info[key] = value[kept].mean().item() if kept.any() else float("nan")
        u, target = meanflow_target(self.velocity_field(net), z, r, t, v, cond, drop)
        squared_error = (u - target).pow(2).flatten(1).sum(dim=1)
        weight = (squared_error.detach() + c.adaptive_eps).pow(-c.adaptive_power)
        loss = (weight * squared_error).mean()
        info["loss"] = loss.item()
        info["mse"] = squared_error.mean().item() / u[0].numel()
        return loss, info

    @torch.no_grad()
    def sample(
        self, net: nn.Module, cond: torch.Tensor, generator: torch.Generator | None = None, steps: int | None = None
    ) -> torch.Tensor:
        """Normalized action chunks (B, T, A) from noise in ``steps`` average-velocity jumps from t = 1 to 0.

        One step (the default) is A_0 = A_1 - u(A_1, 0, 1 | c): one conditional network
        evaluation per chunk; k steps jump over [1 - (i+1)/k, 1 - i/k], i = 0..k-1.
        Deterministic given a seeded generator; the null branch is never evaluated (CFG lives
        in the trained network).
        """
        steps = self.config.inference_steps if steps is None else steps
        if steps < 1:
            raise ValueError(f"steps must be >= 1, got {steps}")
        batch = cond.shape[0]
        z = draw("randn", (batch, net.horizon, net.action_dim), cond, generator)
        times = torch.linspace(1.0, 0.0, steps + 1, dtype=cond.dtype, device=cond.device)
        velocity = self.velocity_field(net)
        for t_value, r_value in zip(times[:-1], times[1:], strict=True):
            t, r = t_value.expand(batch), r_value.expand(batch)
            z = z - (t_value - r_value) * velocity(z, r, t, cond)
        return z
