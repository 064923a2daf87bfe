"""Training on a GPU (`--device cuda`): skipped where torch sees none; run on a GPU machine.

The CPU suite cannot see a tensor left on the wrong device, so these check the device path
itself: windows drawn on the GPU equal the CPU's, every cloud and state expert takes a training
step there, and `train_policy` trains and saves a checkpoint that acts on the CPU.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

from benchmarks.train import TrainBenchConfig, samples_per_second, synthetic_frames
from collectors.dataset import DemoWindows, WindowConfig
from d2a_agents.policy.agent import PolicyConfig
from d2a_agents.policy.checkpoints import load_policy
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.train import PolicyPreset, TrainPolicyConfig, train_policy

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")

TINY = PolicyConfig(num_points=16, encoder=EncoderConfig(point_widths=(8,), image_widths=(4, 4, 4, 4)),
                    network=VelocityNetConfig(hidden=16, layers=1))


def test_windows_on_the_gpu_equal_the_cpu_windows():
    frames = synthetic_frames(16, episodes=3, length=12)
    config = WindowConfig(obs_keys=("point_cloud", "agent_pos"))
    on_cpu, on_gpu = DemoWindows(frames, config), DemoWindows(frames.to("cuda"), config)
    chosen = torch.tensor([0, 5, len(on_cpu) - 1])
    expected, got = on_cpu.get(chosen), on_gpu.get(chosen)
    assert got["action"].device.type == "cuda"
    for key in (("obs", "point_cloud"), ("obs", "agent_pos"), "action", "episode", "step"):
        torch.testing.assert_close(got[key].cpu(), expected[key])
    batch = on_gpu.sample(8, torch.Generator(device="cuda").manual_seed(0))
    assert batch["action"].shape == (8, 4, 4) and batch["action"].device.type == "cuda"


@pytest.mark.parametrize("algo", ["mp1", "d2a", "dp3", "flowpolicy", "edm", "dp", "mp1-state"])
def test_every_expert_takes_a_training_step_on_the_gpu(algo):
    tiny = PolicyPreset(TINY, steps=1, batch_size=8, learning_rate=1e-3, image_batch_size=2)
    config = TrainBenchConfig(rows=(), steps=2, device="cuda", episodes=1, episode_length=10, rgb_image_size=40)
    assert samples_per_second(tiny, algo, config) > 0


def test_train_policy_on_the_gpu_saves_a_checkpoint_that_acts_on_the_cpu(reach_data, tmp_path):
    out = tmp_path / "run"
    config = TrainPolicyConfig(data=reach_data, out=str(out), policy=dataclasses.replace(TINY, algo="mp1"), steps=4,
                               batch_size=4, eval_episodes=0, device="cuda", progress=False)
    train_policy(config)
    policy, payload = load_policy(out / "policy.pt")
    assert payload["step"] == 4
    assert all(parameter.device.type == "cpu" for parameter in policy.parameters())


def test_a_consistency_student_distils_its_teacher_on_the_gpu(reach_data, tmp_path):
    def run(algo: str, **extra: str) -> TrainPolicyConfig:
        return TrainPolicyConfig(data=reach_data, out=str(tmp_path / algo), policy=dataclasses.replace(TINY, algo=algo),
                                 steps=2, batch_size=4, eval_episodes=0, device="cuda", progress=False, **extra)

    train_policy(run("edm"))
    train_policy(run("cp", teacher=str(tmp_path / "edm" / "policy.pt")))
    student, payload = load_policy(tmp_path / "cp" / "policy.pt")
    assert payload["step"] == 2 and student.config.algo == "cp"
