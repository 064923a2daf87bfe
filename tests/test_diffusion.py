"""The diffusion baseline against independent computations: schedule, noising, DDIM step, sampler, toy fit."""

from __future__ import annotations

import math

import pytest
import torch

from d2a_agents.policy.diffusion import Diffusion, DiffusionConfig
from d2a_agents.policy.networks import VelocityNet, VelocityNetConfig

torch.set_num_threads(1)


class ConstantNet(torch.nn.Module):
    """Returns a fixed prediction and records every call (the DDIM tests need a known output)."""

    def __init__(self, value: torch.Tensor) -> None:
        super().__init__()
        self.value, self.horizon, self.action_dim = value, value.shape[1], value.shape[2]
        self.calls: list[tuple[torch.Tensor, torch.Tensor]] = []

    def forward(self, z: torch.Tensor, r: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        self.calls.append((r.clone(), t.clone()))
        return self.value.expand_as(z)


def _alpha_bar_by_hand(t: int, steps: int = 100, s: float = 0.008) -> float:
    """alphas_cumprod[t] = prod_{i <= t} (1 - min(1 - f((i + 1) / T) / f(i / T), 0.999)), f the cosine."""

    def f(u: float) -> float:
        return math.cos(((u + s) / (1 + s)) * math.pi / 2) ** 2

    product = 1.0
    for i in range(t + 1):
        product *= 1 - min(1 - f((i + 1) / steps) / f(i / steps), 0.999)
    return product


def test_cosine_schedule_matches_formula() -> None:
    diffusion = Diffusion()
    for t in (0, 1, 10, 50, 90, 98, 99):
        assert diffusion.alphas_cumprod[t].item() == pytest.approx(_alpha_bar_by_hand(t), rel=1e-9, abs=1e-15)
    # Away from the cap the product telescopes: abar[t] = f((t + 1) / T) / f(0).
    f0 = math.cos(0.008 / 1.008 * math.pi / 2) ** 2
    expected = math.cos((0.51 + 0.008) / 1.008 * math.pi / 2) ** 2 / f0
    assert diffusion.alphas_cumprod[50].item() == pytest.approx(expected, rel=1e-9)
    # The last beta is the capped one: f(1) = 0 would give beta = 1.
    betas = 1 - diffusion.alphas_cumprod[1:] / diffusion.alphas_cumprod[:-1]
    assert betas[-1].item() == pytest.approx(0.999)
    assert bool((betas[:-1] < 0.999).all())


def test_forward_noising_closed_form() -> None:
    diffusion = Diffusion()
    generator = torch.Generator().manual_seed(0)
    x0 = torch.rand(3, 4, 2, generator=generator) * 2 - 1
    eps = torch.randn(3, 4, 2, generator=generator)
    timesteps = torch.tensor([0, 37, 99])
    noisy = diffusion.add_noise(x0, eps, timesteps)
    for b, t in enumerate(timesteps.tolist()):
        abar = _alpha_bar_by_hand(t)
        expected = math.sqrt(abar) * x0[b] + math.sqrt(1 - abar) * eps[b]
        torch.testing.assert_close(noisy[b], expected)


def test_ddim_step_matches_textbook_update() -> None:
    diffusion = Diffusion(DiffusionConfig(clip_sample=False))
    generator = torch.Generator().manual_seed(1)
    x_t = torch.randn(2, 4, 3, generator=generator)
    eps = torch.randn(1, 4, 3, generator=generator)
    net = ConstantNet(eps)
    for t, t_prev in ((90, 80), (50, 40), (10, 0), (0, -1)):
        abar_t = _alpha_bar_by_hand(t)
        abar_prev = _alpha_bar_by_hand(t_prev) if t_prev >= 0 else 1.0
        x0_pred = (x_t - math.sqrt(1 - abar_t) * eps) / math.sqrt(abar_t)
        expected = math.sqrt(abar_prev) * x0_pred + math.sqrt(1 - abar_prev) * eps
        time = torch.full((2,), t / 100)
        step = diffusion.ddim_step(net(x_t, time, time, torch.zeros(2, 1)), t, t_prev, x_t)
        torch.testing.assert_close(step, expected, rtol=1e-5, atol=1e-5)


def test_ddim_step_clips_the_clean_estimate_and_eta_adds_posterior_noise() -> None:
    x_t = torch.full((1, 1, 2), 0.5)
    eps = torch.tensor([[[-2.0, 0.0]]])
    abar_t, abar_prev = _alpha_bar_by_hand(50), _alpha_bar_by_hand(40)
    x0 = ((x_t - math.sqrt(1 - abar_t) * eps) / math.sqrt(abar_t)).clamp(-1, 1)
    assert x0[0, 0, 0].item() == 1.0 and abs(x0[0, 0, 1].item()) < 1  # only the first is clipped
    clipped = Diffusion().ddim_step(eps, 50, 40, x_t)
    torch.testing.assert_close(clipped, math.sqrt(abar_prev) * x0 + math.sqrt(1 - abar_prev) * eps)
    # eta = 1: the DDPM posterior standard deviation, with the noise drawn from the generator.
    sigma = math.sqrt((1 - abar_prev) / (1 - abar_t) * (1 - abar_t / abar_prev))
    z = torch.randn(1, 1, 2, generator=torch.Generator().manual_seed(5))
    expected = math.sqrt(abar_prev) * x0 + math.sqrt(1 - abar_prev - sigma**2) * eps + sigma * z
    noisy = Diffusion(DiffusionConfig(eta=1.0)).ddim_step(eps, 50, 40, x_t, torch.Generator().manual_seed(5))
    torch.testing.assert_close(noisy, expected)


def test_sample_prediction_reads_output_as_clean_chunk() -> None:
    diffusion = Diffusion(DiffusionConfig(prediction_type="sample"))
    x_t, x0 = torch.randn(2, 3, 2), torch.rand(2, 3, 2) - 0.5
    abar_t, abar_prev = _alpha_bar_by_hand(60), _alpha_bar_by_hand(50)
    eps = (x_t - math.sqrt(abar_t) * x0) / math.sqrt(1 - abar_t)
    expected = math.sqrt(abar_prev) * x0 + math.sqrt(1 - abar_prev) * eps
    torch.testing.assert_close(diffusion.ddim_step(x0, 60, 50, x_t), expected, rtol=1e-5, atol=1e-5)
    # Training regresses the clean chunk: a net that outputs it exactly has zero loss.
    actions = torch.rand(4, 3, 2) - 0.5
    loss, _ = diffusion.loss(lambda z, r, t, c: actions, actions, torch.zeros(4, 1))
    assert loss.item() == 0.0


def test_sample_evaluates_the_network_once_per_inference_step() -> None:
    diffusion = Diffusion()
    net = ConstantNet(torch.zeros(1, 4, 3))
    actions = diffusion.sample(net, torch.zeros(5, 7), torch.Generator().manual_seed(0))
    assert actions.shape == (5, 4, 3)
    assert len(net.calls) == 10 == diffusion.config.inference_steps
    times = [t[0].item() for _, t in net.calls]
    assert times == pytest.approx([k / 100 for k in range(90, -1, -10)])
    assert all(torch.equal(r, t) for r, t in net.calls)
    assert float(actions.abs().max()) <= 1.0  # the last step returns the clipped clean estimate
    net.calls.clear()
    diffusion.sample(net, torch.zeros(5, 7), steps=4)
    assert len(net.calls) == 4
    with pytest.raises(ValueError):
        diffusion.inference_timesteps(101)
    with pytest.raises(ValueError):
        DiffusionConfig(prediction_type="v_prediction")


def test_loss_is_the_noise_mse_at_uniform_timesteps() -> None:
    diffusion = Diffusion()
    actions = torch.rand(4096, 2, 2) * 2 - 1
    captured: dict[str, torch.Tensor] = {}

    def net(z: torch.Tensor, r: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        captured.update(z=z, t=t)
        return torch.zeros_like(z)

    loss, info = diffusion.loss(net, actions, torch.zeros(4096, 3), torch.Generator().manual_seed(0))
    timesteps = torch.round(captured["t"] * 100).long()
    assert int(timesteps.min()) == 0 and int(timesteps.max()) == 99
    assert abs(timesteps.float().mean().item() - 49.5) < 2.0
    # With a zero prediction the loss is E[eps^2]; recover eps from z and check the closed form holds.
    abar = diffusion.alphas_cumprod[timesteps].float()[:, None, None]
    eps = (captured["z"] - abar.sqrt() * actions) / (1 - abar).sqrt()
    assert loss.item() == pytest.approx(eps.pow(2).mean().item(), rel=1e-4)
    assert info["mse"] == pytest.approx(loss.item())
    assert abs(eps.mean().item()) < 0.03 and abs(eps.std().item() - 1) < 0.03


CENTRES = torch.tensor([[0.5, 0.5], [-0.5, 0.5], [0.5, -0.5], [-0.5, -0.5]])


def _mixture(n: int, generator: torch.Generator) -> torch.Tensor:
    """Four Gaussians (std 0.08) at (+-0.5, +-0.5), as action chunks (n, 1, 2)."""
    index = torch.randint(4, (n,), generator=generator)
    return (CENTRES[index] + 0.08 * torch.randn(n, 2, generator=generator))[:, None, :]


def _energy_distance(x: torch.Tensor, y: torch.Tensor) -> float:
    """2 E|X - Y| - E|X - X'| - E|Y - Y'| (zero iff the distributions agree)."""
    x, y = x.flatten(1), y.flatten(1)
    return (2 * torch.cdist(x, y).mean() - torch.cdist(x, x).mean() - torch.cdist(y, y).mean()).item()


def test_toy_mixture_is_learned() -> None:
    torch.manual_seed(0)
    net = VelocityNet(VelocityNetConfig(hidden=128, layers=3, time_embed_dim=32), horizon=1, action_dim=2, cond_dim=4)
    diffusion = Diffusion()
    reference = _mixture(1000, torch.Generator().manual_seed(100))
    cond = torch.zeros(1000, 4)
    untrained = _energy_distance(diffusion.sample(net, cond, torch.Generator().manual_seed(3)), reference)

    steps, generator = 600, torch.Generator().manual_seed(0)
    optimizer = torch.optim.Adam(net.parameters(), lr=2e-3)
    schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: 0.5 * (1 + math.cos(math.pi * s / steps)))
    for _ in range(steps):
        loss, _ = diffusion.loss(net, _mixture(256, generator), torch.zeros(256, 4), generator)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()

    samples = diffusion.sample(net, cond, torch.Generator().manual_seed(3))
    trained = _energy_distance(samples, reference)
    floor = _energy_distance(_mixture(1000, torch.Generator().manual_seed(101)), reference)
    # Measured (4 seeds): untrained 0.35, trained 0.005-0.008, two data samples 0.001.
    assert untrained > 0.2
    assert trained < 0.03 and trained < 0.1 * untrained, (untrained, trained, floor)
    near = (samples[:, 0, None, :] - CENTRES[None]).norm(dim=-1) < 0.3  # (n, 4)
    assert near.any(dim=1).float().mean().item() > 0.85
    assert near.float().mean(dim=0).min().item() > 0.12  # every mode is covered


def test_seeded_generator_reproduces_loss_and_samples() -> None:
    torch.manual_seed(0)
    net = VelocityNet(VelocityNetConfig(hidden=32, layers=2), horizon=4, action_dim=3, cond_dim=5)
    torch.nn.init.normal_(net.output.weight, std=0.1)  # a non-trivial output
    diffusion = Diffusion()
    actions, cond = torch.rand(8, 4, 3) * 2 - 1, torch.randn(8, 5)

    def run(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        loss, _ = diffusion.loss(net, actions, cond, torch.Generator().manual_seed(seed))
        return loss.detach(), diffusion.sample(net, cond, torch.Generator().manual_seed(seed))

    (loss_a, sample_a), (loss_b, sample_b), (loss_c, sample_c) = run(7), run(7), run(8)
    assert torch.equal(loss_a, loss_b) and torch.equal(sample_a, sample_b)
    assert not torch.equal(loss_a, loss_c) and not torch.equal(sample_a, sample_c)
    stochastic = Diffusion(DiffusionConfig(eta=1.0))  # the generator also drives the per-step noise
    first, second = (stochastic.sample(net, cond, torch.Generator().manual_seed(7)) for _ in range(2))
    assert torch.equal(first, second) and not torch.equal(first, sample_a)
