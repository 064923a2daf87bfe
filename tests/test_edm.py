"""EDM against closed forms: the Karras schedule, the preconditioning, a zero loss at the ideal
denoiser of a one-point data set, and the Heun sampler carrying N(0, sigma_max^2) onto a
Gaussian data distribution through its exact denoiser."""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from d2a_agents.policy.edm import EDM, EDMConfig, karras_sigmas


class IdealNet(nn.Module):
    """The network output F that makes D(x; sigma) equal ``ideal(x, sigma)``: F = (ideal - c_skip x) / c_out,
    with sigma read back from the time input (ln sigma / 4) and x from the scaled input."""

    horizon, action_dim = 2, 3

    def __init__(self, edm: EDM, ideal) -> None:
        super().__init__()
        self.edm, self.ideal = edm, ideal

    def forward(self, scaled, r, t, cond):
        sigma = (4 * t).exp()
        c_skip, c_out, c_in = (c.reshape(-1, 1, 1) for c in self.edm.scalings(sigma))
        x = scaled / c_in
        return (self.ideal(x, sigma.reshape(-1, 1, 1)) - c_skip * x) / c_out


def test_the_karras_schedule_matches_its_formula():
    sigmas = karras_sigmas(5, 0.02, 80.0, 7.0)
    assert sigmas[0] == pytest.approx(80.0) and sigmas[-1] == pytest.approx(0.02)
    middle = ((80.0 ** (1 / 7) + 0.02 ** (1 / 7)) / 2) ** 7  # i = 2 of 4: halfway in sigma^(1/7)
    assert sigmas[2] == pytest.approx(middle)
    assert all(a > b for a, b in zip(sigmas[:-1], sigmas[1:], strict=True))
    assert EDM(EDMConfig(inference_steps=3)).schedule()[-1] == 0.0


def test_the_preconditioning_keeps_unit_scale():
    """With sd = 0.5: at sigma = sd, c_skip = 1/2, c_out = sd / sqrt(2), c_in = 1 / (sd sqrt(2))."""
    c_skip, c_out, c_in = EDM().scalings(torch.tensor([0.5]))
    assert c_skip.item() == pytest.approx(0.5)
    assert c_out.item() == pytest.approx(0.5 / math.sqrt(2))
    assert c_in.item() == pytest.approx(1 / (0.5 * math.sqrt(2)))


def test_the_loss_vanishes_at_the_ideal_denoiser_of_a_single_chunk():
    edm = EDM()
    chunk = torch.tensor([[0.3, -0.2, 0.9], [0.0, 0.5, -0.7]])
    net = IdealNet(edm, lambda x, sigma: chunk.expand_as(x))
    actions = chunk.expand(16, 2, 3)
    loss, _ = edm.loss(net, actions, torch.zeros(16, 1), torch.Generator().manual_seed(0))
    assert loss.item() < 1e-8
    off, _ = edm.loss(IdealNet(edm, lambda x, sigma: torch.zeros_like(x)), actions, torch.zeros(16, 1),
                      torch.Generator().manual_seed(0))
    assert off.item() > 0.1


def test_heun_follows_the_probability_flow_of_a_gaussian_and_converges():
    """Data N(0, s^2): the exact denoiser is s^2 / (s^2 + sigma^2) x and the probability-flow ODE
    scales x by sqrt(s^2 + sigma^2), so a start x at sigma_max ends at x s^2 / sqrt((s^2 +
    sigma_min^2)(s^2 + sigma_max^2)) after the last (Euler) step. Heun's error falls with the
    steps and is under 1 % at 50."""
    s, start = 0.3, 80.0
    exact = start * s**2 / math.sqrt((s**2 + 0.02**2) * (s**2 + 80.0**2))
    errors = []
    for steps in (5, 18, 50):
        edm = EDM(EDMConfig(inference_steps=steps, clip_sample=False))
        net = IdealNet(edm, lambda x, sigma: s**2 / (s**2 + sigma**2) * x)
        x = torch.full((1, 2, 3), start, dtype=torch.float64)
        levels = [torch.tensor([level], dtype=torch.float64) for level in edm.schedule()[:-1]]
        cond = torch.zeros(1, 1, dtype=torch.float64)
        for sigma, sigma_next in zip(levels[:-1], levels[1:], strict=True):
            x = edm.heun_step(net, x, sigma, sigma_next, cond)
        x = x - levels[-1] * edm.slope(net, x, levels[-1], cond)  # the final Euler step to sigma = 0
        errors.append(abs(x[0, 0, 0].item() - exact) / exact)
    assert errors[0] > errors[1] > errors[2] and errors[2] < 0.01, errors


def test_sampling_starts_from_sigma_max_noise_and_clips():
    edm = EDM(EDMConfig(inference_steps=1))
    net = IdealNet(edm, lambda x, sigma: torch.full_like(x, 3.0))  # a denoiser far outside [-1, 1]
    chunks = edm.sample(net, torch.zeros(4, 1), torch.Generator().manual_seed(0))
    assert chunks.shape == (4, 2, 3) and torch.equal(chunks, torch.ones_like(chunks))
