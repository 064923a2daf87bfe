"""The consistency student against closed forms: its jump's boundary, the exact trajectory map of
Gaussian data (one-step sampling lands on the data distribution; the trajectory loss vanishes
up to the teacher's Heun error), and a student that must have a teacher."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from d2a_agents.policy.consistency_policy import ConsistencyPolicyConfig, ConsistencyTrajectory
from d2a_agents.policy.edm import EDM
from d2a_agents.policy.networks import VelocityNet, VelocityNetConfig
from tests.test_edm import IdealNet

SPREAD = 0.3  # data N(0, SPREAD^2) per element


def exact_jump(x: torch.Tensor, t: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """The probability-flow map of Gaussian data from level t to level s: x scales by sqrt(SPREAD^2 + sigma^2)."""
    return x * ((SPREAD**2 + s**2) / (SPREAD**2 + t**2)).sqrt()


class IdealStudent(nn.Module):
    """The network output that makes the student's jump the exact one (its denoiser at s = t the exact D)."""

    horizon, action_dim = 2, 3

    def __init__(self, student: ConsistencyTrajectory) -> None:
        super().__init__()
        self.student = student

    def forward(self, scaled, r, t, cond):
        t_level, s_level = ((4 * time).exp().reshape(-1, 1, 1) for time in (t, r))
        c_skip, c_out, c_in = (c.reshape(-1, 1, 1) for c in self.student.edm.scalings(t_level.flatten()))
        x = scaled / c_in
        ratio = s_level / t_level
        same = ratio > 1 - 1e-6
        exact = SPREAD**2 / (SPREAD**2 + t_level**2) * x
        g = torch.where(same, exact, (exact_jump(x, t_level, s_level) - ratio * x) / (1 - ratio).clamp(min=1e-6))
        return (g - c_skip * x) / c_out


def test_a_jump_to_its_own_level_is_the_identity():
    net = VelocityNet(VelocityNetConfig(hidden=16, layers=1, time_scale=1000.0), 2, 3, 4)
    nn.init.normal_(net.output.weight)  # a network that does move its input
    student = ConsistencyTrajectory()
    x, t, cond = torch.randn(5, 2, 3), torch.rand(5) * 10 + 0.1, torch.randn(5, 4)
    torch.testing.assert_close(student.jump(net, x, t, t, cond), x)
    assert not torch.allclose(student.jump(net, x, t, t / 2, cond), x)


def test_one_jump_of_the_exact_student_lands_on_the_data_distribution():
    student = ConsistencyTrajectory()  # EDM's default levels: sigma 80 -> 0.02
    samples = student.sample(IdealStudent(student), torch.zeros(20000, 1), torch.Generator().manual_seed(0))
    assert samples.std().item() == pytest.approx(SPREAD, rel=0.02)


def test_the_trajectory_loss_vanishes_for_the_exact_student_and_teacher():
    teacher = IdealNet(EDM(), lambda x, sigma: SPREAD**2 / (SPREAD**2 + sigma**2) * x)
    student = ConsistencyTrajectory(ConsistencyPolicyConfig(bins=40), teacher=teacher)
    actions = SPREAD * torch.randn(512, 2, 3, generator=torch.Generator().manual_seed(1))
    cond = torch.zeros(512, 1)
    _, exact = student.loss(IdealStudent(student), actions, cond, torch.Generator().manual_seed(2))

    class Zero(IdealStudent):
        def forward(self, scaled, r, t, cond):
            return torch.zeros_like(scaled)

    _, wrong = student.loss(Zero(student), actions, cond, torch.Generator().manual_seed(2))
    assert exact["trajectory"] < 1e-4 and wrong["trajectory"] > 100 * exact["trajectory"], (exact, wrong)


def test_a_student_needs_a_teacher_to_train():
    with pytest.raises(ValueError, match="EDM teacher"):
        ConsistencyTrajectory().loss(IdealStudent(ConsistencyTrajectory()), torch.zeros(2, 2, 3), torch.zeros(2, 1))
