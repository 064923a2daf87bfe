"""The perception check: on a synthetic task where one input alone holds the answer, a trained
policy's one-step error rises when that input is shuffled across windows, not the other."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from collectors.dataset import DemoWindows, WindowConfig
from d2a_agents.policy.agent import Policy, PolicyConfig
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.perception import reliance
from d2a_agents.policy.train import fit_policy_normalizers, training_step

EPISODES, STEPS, POINTS = 24, 6, 16


def synthetic_frames(answer_in: str, seed: int = 0) -> TensorDict:
    """Each episode has a goal g in [-1, 1]^2 and every action is (g, 0, 0). With
    ``answer_in="cloud"`` the cloud is a blob at (g, 0) and ``agent_pos`` is constant;
    with ``"agent_pos"`` it is the other way round; with ``"imagined"`` only the imagined
    cloud sits at (g, 0). The clouds that hold no answer are blobs at the origin."""
    generator = torch.Generator().manual_seed(seed)
    goals = torch.rand(EPISODES, 2, generator=generator) * 2 - 1
    rows = goals.repeat_interleave(STEPS, dim=0)
    n = rows.shape[0]
    blob = 0.05 * torch.randn(n, POINTS, 3, generator=generator)
    informative_cloud = blob + torch.cat([rows, torch.zeros(n, 1)], dim=1)[:, None]
    informative_pos = torch.cat([rows, torch.zeros(n, 2)], dim=1)
    cloud = informative_cloud if answer_in == "cloud" else blob
    agent_pos = informative_pos if answer_in == "agent_pos" else torch.zeros(n, 4)
    imagined = informative_cloud if answer_in == "imagined" else blob.flip(0)
    return TensorDict({
        "point_cloud": cloud, "agent_pos": agent_pos, "imagined_point_cloud": imagined,
        "action": torch.cat([rows, torch.zeros(n, 2)], dim=1),
        "episode": torch.arange(EPISODES).repeat_interleave(STEPS),
    }, batch_size=[n])


@pytest.mark.parametrize("algo, answer_in", [
    ("mp1", "cloud"), ("mp1", "agent_pos"), ("d2a-no-cfg", "imagined"), ("d2a-no-cfg", "cloud"),
])
def test_shuffling_the_informative_input_raises_the_error(algo, answer_in):
    torch.set_num_threads(1)
    torch.manual_seed(0)
    config = PolicyConfig(algo=algo, num_points=POINTS, adaptive_power=0.0, horizon=2, n_obs_steps=1,
                          n_action_steps=2, encoder=EncoderConfig(point_widths=(32, 32)),
                          network=VelocityNetConfig(hidden=64, layers=2))
    frames = synthetic_frames(answer_in)
    policy = Policy(config, 4, 4, fit_policy_normalizers(frames, config))
    windows = DemoWindows(frames, WindowConfig(2, 1, 2, config.observation_keys))
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    generator = torch.Generator().manual_seed(0)
    for _ in range(300):
        training_step(policy, optimizer, windows, 64, generator)

    batch = windows.get(torch.arange(len(windows)))
    result = reliance(policy, {key: batch["obs", key] for key in config.observation_keys}, batch["action"])
    assert result.windows == len(windows)
    informative = {"cloud": result.cloud_ratio, "agent_pos": result.state_ratio,
                   "imagined": result.imagined_ratio}[answer_in]
    ignored = [result.cloud_ratio if answer_in == "agent_pos" else result.state_ratio]
    if algo == "d2a-no-cfg":
        assert result.cloud_ratio > 2.0, result  # shuffling both clouds shuffles the imagined one too
        ignored += [result.imagined_ratio] if answer_in == "cloud" else []
    else:
        assert result.imagined_ratio is None
    assert informative > 2.0, result
    assert all(ratio < 1.5 for ratio in ignored), result
    assert policy.training  # the check leaves the mode as it found it


def test_reliance_needs_two_windows():
    config = PolicyConfig(algo="mp1", num_points=POINTS, encoder=EncoderConfig(point_widths=(8,)),
                          network=VelocityNetConfig(hidden=8, layers=1))
    frames = synthetic_frames("cloud")
    policy = Policy(config, 4, 4, fit_policy_normalizers(frames, config))
    one = {"point_cloud": frames["point_cloud"][:1, None], "agent_pos": frames["agent_pos"][:1, None]}
    with pytest.raises(ValueError, match="at least 2"):
        reliance(policy, one, torch.zeros(1, 4, 4))
