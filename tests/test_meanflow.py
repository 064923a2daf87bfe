"""MeanFlow expert: eq. 5 target against finite differences, a learned 2-D mixture, eq. 6-7
against hand values, the unconditional branch, evaluation counts and sampler determinism."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from d2a_agents.policy import networks
from d2a_agents.policy.meanflow import MeanFlow, MeanFlowConfig, cfg_weight, meanflow_target
from d2a_agents.policy.networks import VelocityNet, VelocityNetConfig


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def random_velocity_net(horizon: int, action_dim: int, cond_dim: int, seed: int = 0) -> VelocityNet:
    """A small VelocityNet whose zero-initialised output layer and null embedding are randomised."""
    torch.manual_seed(seed)
    net = VelocityNet(VelocityNetConfig(hidden=32, layers=2, time_embed_dim=16), horizon, action_dim, cond_dim)
    nn.init.normal_(net.output.weight, std=0.3)
    nn.init.normal_(net.output.bias, std=0.3)
    nn.init.normal_(net.null_condition)
    return net


class CountingNet(nn.Module):
    """Wraps a velocity net; counts all calls and the calls with a dropped (unconditional) row."""

    def __init__(self, inner: nn.Module) -> None:
        super().__init__()
        self.inner, self.horizon, self.action_dim = inner, inner.horizon, inner.action_dim
        self.calls, self.unconditional_calls = 0, 0

    def forward(self, z, r, t, cond, drop=None):
        self.calls += 1
        self.unconditional_calls += int(drop is not None and bool(drop.any()))
        return self.inner(z, r, t, cond, drop)


def float64_time_embedding(t: torch.Tensor, dim: int, scale: float = 1.0) -> torch.Tensor:
    """networks.time_embedding's formula kept in float64 (the original computes in float32)."""
    half = dim // 2
    frequencies = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float64) / half)
    angles = scale * t[:, None] * frequencies[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


@pytest.mark.parametrize("exact_float64", [True, False])
def test_jvp_target_matches_finite_differences(monkeypatch, exact_float64):
    """u_tgt = v - (t - r)(v . grad_z u + d_t u), the derivative by central differences along (v, 0, 1).

    With the time embedding in float64 the whole net is float64 and the match is tight; the
    shipped embedding rounds t to float32 (about 6e-8), which limits the difference quotient
    to about 1e-3 relative.
    """
    if exact_float64:
        monkeypatch.setattr(networks, "time_embedding", float64_time_embedding)
    net = random_velocity_net(horizon=3, action_dim=2, cond_dim=5).double()
    gen = torch.Generator().manual_seed(1)
    batch = 6
    z = torch.randn(batch, 3, 2, generator=gen, dtype=torch.float64)
    v = torch.randn(batch, 3, 2, generator=gen, dtype=torch.float64)
    t = 0.1 + 0.8 * torch.rand(batch, generator=gen, dtype=torch.float64)
    r = t * torch.rand(batch, generator=gen, dtype=torch.float64)
    cond = torch.randn(batch, 5, generator=gen, dtype=torch.float64)
    drop = torch.tensor([True, False] * 3)

    u, target = meanflow_target(net, z, r, t, v, cond, drop)

    eps = 1e-7 if exact_float64 else 3e-5
    with torch.no_grad():
        derivative = (net(z + eps * v, r, t + eps, cond, drop) - net(z - eps * v, r, t - eps, cond, drop)) / (2 * eps)
        expected = v - (t - r)[:, None, None] * derivative
        torch.testing.assert_close(u, net(z, r, t, cond, drop), rtol=1e-12, atol=1e-12)
    assert not target.requires_grad and u.requires_grad
    scale = (expected - v).abs().max()  # the size of the JVP term the check is about
    tolerance = 1e-7 if exact_float64 else 5e-3
    assert (target - expected).abs().max() <= tolerance * scale


def test_time_pairs_follow_the_logit_normal_design():
    """r <= t; r = t on flow_ratio_equal of the batch; otherwise {r, t} are two logit-normal draws."""
    config = MeanFlowConfig(flow_ratio_equal=0.3)
    r, t = MeanFlow(config).sample_times(40000, torch.zeros(1), torch.Generator().manual_seed(0))
    assert torch.all(r <= t) and torch.all((r > 0) & (t < 1))
    equal = r == t
    assert equal.float().mean().item() == pytest.approx(0.3, abs=0.01)
    logits = torch.logit(torch.cat([r[~equal], t[~equal]]).double())
    assert logits.mean().item() == pytest.approx(config.time_mean, abs=0.02)
    assert logits.std().item() == pytest.approx(config.time_std, abs=0.02)


class ToyNet(nn.Module):
    """A plain MLP on [z, t, t - r, condition or learned null]: the velocity-net interface with
    smooth time inputs, small enough to train in seconds."""

    def __init__(self, cond_dim: int, hidden: int = 128) -> None:
        super().__init__()
        self.horizon, self.action_dim = 1, 2
        self.null_condition = nn.Parameter(torch.zeros(cond_dim))
        self.mlp = nn.Sequential(
            nn.Linear(2 + 2 + cond_dim, hidden), nn.SiLU(), nn.Linear(hidden, hidden), nn.SiLU(),
            nn.Linear(hidden, hidden), nn.SiLU(), nn.Linear(hidden, 2),
        )

    def forward(self, z, r, t, cond, drop=None):
        if drop is not None:
            cond = torch.where(drop[:, None], self.null_condition.expand_as(cond), cond)
        return self.mlp(torch.cat([z.flatten(1), t[:, None], (t - r)[:, None], cond], dim=-1)).reshape(-1, 1, 2)


def four_gaussians(n: int, generator: torch.Generator) -> torch.Tensor:
    """(n, 1, 2) "action chunks": equal mixture of N(centre, 0.08^2 I), centres 0.6 (cos, sin)(pi/4 + k pi/2)."""
    angle = torch.randint(4, (n,), generator=generator) * math.pi / 2 + math.pi / 4
    centres = 0.6 * torch.stack([angle.cos(), angle.sin()], dim=-1)
    return (centres + 0.08 * torch.randn(n, 2, generator=generator))[:, None, :]


def energy_distance(x: torch.Tensor, y: torch.Tensor) -> float:
    """Squared energy distance 2 E|X - Y| - E|X - X'| - E|Y - Y'| (V-statistic): 0 iff same law."""
    x, y = x.flatten(1).double(), y.flatten(1).double()
    return (2 * torch.cdist(x, y).mean() - torch.cdist(x, x).mean() - torch.cdist(y, y).mean()).item()


@pytest.mark.parametrize(
    "config",
    [MeanFlowConfig(cfg_enabled=False), MeanFlowConfig(cfg_similarity="prediction")],
    ids=["no-cfg", "cfg-prediction-gate"],
)
def test_one_step_samples_learn_a_gaussian_mixture(config):
    """2000 Adam steps on four Gaussians (constant condition); one-step samples vs held-out
    data by energy distance.

    References at n = 2000 (measured): two data samples ~5e-4 (the noise floor); N(0, I),
    what an untrained net roughly gives, ~0.19; the best single Gaussian (the mixture's mean
    and covariance) ~0.032. Bound: below half of that Gaussian's distance, which only a model
    that separates the modes reaches, and below a tenth of the untrained model's distance.
    Measured over seeds 0-3: 0.008-0.014 without CFG, 0.006-0.012 with the prediction gate.
    (The paper's gate, rho = cos(v, u_null), gives 0.04-0.05 here: samples pulled towards the
    centre, see the meanflow module docstring.)
    """
    torch.manual_seed(0)
    net = ToyNet(cond_dim=2)
    expert = MeanFlow(config)
    steps, batch = 2000, 256
    optimizer = torch.optim.Adam(net.parameters(), lr=2e-3)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1 - step / steps)
    gen = torch.Generator().manual_seed(0)
    data = four_gaussians(2000, torch.Generator().manual_seed(1))
    cond = torch.ones(2000, 2)

    def distance() -> float:
        return energy_distance(expert.sample(net, cond, generator=torch.Generator().manual_seed(5)), data)

    untrained = distance()
    for _ in range(steps):
        loss, _ = expert.loss(net, four_gaussians(batch, gen), cond[:batch], generator=gen)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
    trained = distance()

    covariance = torch.cov(data.flatten(1).T)
    gaussian = data.flatten(1).mean(0) + torch.randn(2000, 2, generator=gen) @ torch.linalg.cholesky(covariance).T
    best_gaussian = energy_distance(gaussian, data)
    assert trained < 0.5 * best_gaussian, (trained, best_gaussian)
    assert trained < 0.1 * untrained, (trained, untrained)


def test_cfg_weight_follows_eq7():
    """w = 0 at and below tau_l, 1 at and above tau_h, (rho - tau_l) / (tau_h - tau_l) between."""
    rho = torch.tensor([-0.5, 0.2, 0.3, 0.4, 0.6, 0.9])
    expected = torch.tensor([0.0, 0.0, 0.25, 0.5, 1.0, 1.0])
    torch.testing.assert_close(cfg_weight(rho, 0.2, 0.6), expected)
    with pytest.raises(ValueError, match="tau_l < tau_h"):
        MeanFlowConfig(tau_l=0.5, tau_h=0.5)


class ConstantNet(nn.Module):
    """u = ``null`` where the condition is dropped, ``conditional`` elsewhere, whatever z, r, t."""

    def __init__(self, null: list[float], conditional: list[float]) -> None:
        super().__init__()
        self.null, self.conditional = torch.tensor(null), torch.tensor(conditional)

    def forward(self, z, r, t, cond, drop=None):
        dropped = torch.zeros(z.shape[0], dtype=torch.bool) if drop is None else drop
        return torch.where(dropped[:, None, None], self.null, self.conditional).expand_as(z)


def test_guided_velocity_follows_eq6_with_hand_values():
    """v_cfg = w v + (1 - w) u_null, rho = cos(v, u_null) (paper) or cos(u_cond, u_null)."""
    net = ConstantNet(null=[1.0, 0.0], conditional=[1.0, 1.0])  # cos(u_cond, u_null) = 0.707 -> w = 1
    v = torch.tensor([[[1.0, 2.0]], [[-1.0, 1.0]], [[3.0, 0.0]]])  # cos with u_null: 1/sqrt(5), -0.707, 1
    z, t, cond = torch.zeros(3, 1, 2), torch.full((3,), 0.5), torch.zeros(3, 1)
    w_first = (1 / math.sqrt(5)) / 0.5
    expected = torch.tensor([[[w_first + (1 - w_first), 2 * w_first]], [[1.0, 0.0]], [[3.0, 0.0]]])

    by_velocity = MeanFlow(MeanFlowConfig(tau_l=0.0, tau_h=0.5, cfg_similarity="velocity"))
    v_cfg, w, rho = by_velocity.guided_velocity(net, z, t, v, cond)
    torch.testing.assert_close(rho, torch.tensor([1 / math.sqrt(5), -1 / math.sqrt(2), 1.0]))
    torch.testing.assert_close(w, torch.tensor([w_first, 0.0, 1.0]))
    torch.testing.assert_close(v_cfg, expected)

    by_prediction = MeanFlow(MeanFlowConfig(cfg_similarity="prediction"))
    v_cfg, w, rho = by_prediction.guided_velocity(net, z, t, v, cond)
    torch.testing.assert_close(rho, torch.full((3,), 1 / math.sqrt(2)))
    torch.testing.assert_close(v_cfg, v)


def test_amplifying_guidance_moves_away_from_the_unconditional_field():
    """cfg_guidance="amplify": v_cfg = s v + (1 - s) u_null, s = 1 + k w (hand values, velocity gate)."""
    net = ConstantNet(null=[1.0, 0.0], conditional=[1.0, 1.0])
    v = torch.tensor([[[1.0, 2.0]], [[-1.0, 1.0]], [[3.0, 0.0]]])  # w = 2/sqrt(5), 0, 1
    z, t, cond = torch.zeros(3, 1, 2), torch.full((3,), 0.5), torch.zeros(3, 1)
    expert = MeanFlow(MeanFlowConfig(tau_l=0.0, tau_h=0.5, cfg_similarity="velocity", cfg_guidance="amplify",
                                     cfg_scale=2.0))
    v_cfg, w, _ = expert.guided_velocity(net, z, t, v, cond)
    scale = 1 + 2.0 * (2 / math.sqrt(5))
    expected = torch.tensor([[[scale * 1.0 + (1 - scale) * 1.0, scale * 2.0]],  # first: s = 1 + 2 w
                             [[-1.0, 1.0]],  # w = 0: plain v
                             [[3 * 3.0 - 2 * 1.0, 0.0]]])  # w = 1: s = 3
    torch.testing.assert_close(w, torch.tensor([2 / math.sqrt(5), 0.0, 1.0]))
    torch.testing.assert_close(v_cfg, expected)
    with pytest.raises(ValueError, match="cfg_guidance"):
        MeanFlowConfig(cfg_guidance="extrapolate")


def test_dropped_rows_ignore_the_condition():
    net = random_velocity_net(horizon=4, action_dim=3, cond_dim=6)
    gen = torch.Generator().manual_seed(0)
    z, r, t = torch.randn(5, 4, 3, generator=gen), torch.full((5,), 0.2), torch.full((5,), 0.7)
    cond_a, cond_b = torch.randn(5, 6, generator=gen), torch.randn(5, 6, generator=gen)
    dropped = torch.ones(5, dtype=torch.bool)
    with torch.no_grad():
        assert torch.equal(net(z, r, t, cond_a, dropped), net(z, r, t, cond_b, dropped))
        difference = (net(z, r, t, cond_a, ~dropped) - net(z, r, t, cond_b, ~dropped)).flatten(1).abs().amax(1)
    assert torch.all(difference > 1e-3)


def test_loss_drops_the_condition_for_about_drop_probability_of_the_batch():
    """The rows of the condition that get no gradient are the dropped ones: ~10 % of 4000."""
    net = random_velocity_net(horizon=2, action_dim=2, cond_dim=3)
    batch = 4000
    gen = torch.Generator().manual_seed(0)
    cond = torch.randn(batch, 3, generator=gen, requires_grad=True)
    actions = torch.rand(batch, 2, 2, generator=gen) * 2 - 1
    loss, info = MeanFlow(MeanFlowConfig(drop_probability=0.1)).loss(net, actions, cond, generator=gen)
    loss.backward()
    no_gradient = (cond.grad.abs().amax(dim=1) == 0).float().mean().item()
    assert no_gradient == pytest.approx(0.1, abs=0.025)  # binomial std 0.005
    assert info["drop_fraction"] == pytest.approx(no_gradient)
    assert net.null_condition.grad.abs().sum() > 0
    assert set(info) == {"loss", "mse", "drop_fraction", "cfg_weight", "cfg_rho", "cfg_active"}


def test_logged_gate_statistics_follow_eq7_inside_the_band():
    """With (tau_l, tau_h) = (-1, 1) every rho lies inside the band: w = (rho + 1) / 2 for each
    sample, so the batch means obey the same relation and every sample counts as changed."""
    net = random_velocity_net(horizon=2, action_dim=2, cond_dim=3)
    gen = torch.Generator().manual_seed(1)
    cond, actions = torch.randn(256, 3, generator=gen), torch.rand(256, 2, 2, generator=gen) * 2 - 1
    _, info = MeanFlow(MeanFlowConfig(tau_l=-1.0, tau_h=1.0)).loss(net, actions, cond, generator=gen)
    assert info["cfg_weight"] == pytest.approx((info["cfg_rho"] + 1) / 2, abs=1e-6)
    assert info["cfg_active"] == 1.0


@pytest.mark.parametrize("similarity", ["velocity", "prediction"])
def test_unconditional_evaluations_only_in_cfg_training(similarity):
    """No CFG: no dropped row anywhere. CFG: dropped rows in training only; sampling is 1 call."""
    cond, actions = torch.randn(8, 3), torch.rand(8, 2, 2) * 2 - 1
    for enabled in (False, True):
        net = CountingNet(random_velocity_net(horizon=2, action_dim=2, cond_dim=3))
        expert = MeanFlow(MeanFlowConfig(cfg_enabled=enabled, cfg_similarity=similarity))
        loss, info = expert.loss(net, actions, cond, generator=torch.Generator().manual_seed(0))
        loss.backward()
        assert (net.unconditional_calls > 0) == enabled
        assert ("cfg_weight" in info) == enabled
        net.calls, net.unconditional_calls = 0, 0
        expert.sample(net, cond, generator=torch.Generator().manual_seed(0))
        assert (net.calls, net.unconditional_calls) == (1, 0)


class PointMassVelocity(nn.Module):
    """The exact average velocity (z - m) / t of the flow from N(0, I) at t = 1 to the point m at t = 0."""

    horizon, action_dim = 2, 3

    def __init__(self, point: torch.Tensor) -> None:
        super().__init__()
        self.point = point

    def forward(self, z, r, t, cond, drop=None):
        return (z - self.point) / t[:, None, None]


def test_sampling_is_reproducible_and_multi_step_lands_on_the_exact_flow():
    net = random_velocity_net(horizon=4, action_dim=3, cond_dim=5)
    cond = torch.randn(6, 5)
    expert = MeanFlow()
    first = expert.sample(net, cond, generator=torch.Generator().manual_seed(7))
    again = expert.sample(net, cond, generator=torch.Generator().manual_seed(7))
    other = expert.sample(net, cond, generator=torch.Generator().manual_seed(8))
    assert first.shape == (6, 4, 3) and torch.equal(first, again) and not torch.equal(first, other)

    counting = CountingNet(net)
    chunks = expert.sample(counting, cond, generator=torch.Generator().manual_seed(7), steps=3)
    assert counting.calls == 3 and chunks.shape == (6, 4, 3) and torch.isfinite(chunks).all()

    point = torch.tensor([[0.5, -0.25, 0.75], [0.0, 1.0, -1.0]])
    for steps in (1, 2, 5):
        landed = MeanFlow(MeanFlowConfig(inference_steps=steps)).sample(
            PointMassVelocity(point), cond, generator=torch.Generator().manual_seed(0)
        )
        torch.testing.assert_close(landed, point.expand(6, 2, 3))


class CleanActionNet(nn.Module):
    """Outputs the clean chunk a(c) = c reshaped, whatever z, r and t are: the exact answer of an
    action-output network where every condition has one demonstrated action."""

    horizon, action_dim = 3, 2

    def forward(self, z, r, t, cond, drop=None):
        return cond.reshape(-1, self.horizon, self.action_dim) + 0 * z


def test_an_action_output_network_reads_as_the_straight_flow_to_its_action():
    """u = (z - x) / t: with x the demonstrated action a, u is A_1 - A_0 on every straight path
    z_t = (1 - t) a + t n, its total derivative along (v, 0, 1) vanishes, so the eq. 5 target is
    v itself, and one jump from noise lands on a; below min_time the division is capped."""
    gen = torch.Generator().manual_seed(0)
    batch = 8
    actions = torch.randn(batch, 3, 2, generator=gen)
    noise = torch.randn(batch, 3, 2, generator=gen)
    t = 0.05 + 0.95 * torch.rand(batch, generator=gen)
    r = t * torch.rand(batch, generator=gen)
    z = (1 - t[:, None, None]) * actions + t[:, None, None] * noise
    v = noise - actions
    expert = MeanFlow(MeanFlowConfig(network_output="action", min_time=0.05))
    u, target = meanflow_target(expert.velocity_field(CleanActionNet()), z, r, t, v, actions.flatten(1), None)
    torch.testing.assert_close(u, v, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(target, v, rtol=1e-4, atol=1e-4)
    landed = expert.sample(CleanActionNet(), actions.flatten(1), generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(landed, actions, rtol=1e-5, atol=1e-5)
    small = torch.full((batch,), 0.01)
    capped = expert.velocity_field(CleanActionNet())(z, small, small, actions.flatten(1))
    torch.testing.assert_close(capped, (z - actions) / 0.05)
    assert MeanFlow().velocity_field(CleanActionNet()).__class__ is CleanActionNet  # "velocity": the net itself
    with pytest.raises(ValueError, match="network_output"):
        MeanFlowConfig(network_output="noise")
