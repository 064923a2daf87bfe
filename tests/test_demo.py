"""The main job, ``d2a demo``, end to end on tiny settings: every stage runs and writes its files."""

from __future__ import annotations

from d2a.demo import DemoConfig, run_demo
from d2a_agents.policy.agent import PolicyConfig
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.train import PolicyPreset
from d2a_agents.world_model.triplane import WorldModelConfig


def test_tiny_demo_runs_every_stage(tmp_path):
    policy = PolicyConfig(num_points=64, encoder=EncoderConfig(point_widths=(16, 32)),
                          network=VelocityNetConfig(hidden=32, layers=2))
    config = DemoConfig(
        task="reach", out=str(tmp_path), episodes=2, world_model=WorldModelConfig(resolution=(16, 16, 8)),
        world_model_steps=2, policy=PolicyPreset(policy, steps=3, batch_size=4, learning_rate=1e-3), eval_episodes=1,
        env_kwargs={"image_size": 48, "num_points": 128},
    )
    figures = run_demo(config)
    assert 0.0 <= figures["success_rate"] <= 1.0 and 0.0 <= figures["full_iou"] <= 1.0
    for name in ("imagination.png", "training_curves.png", "world_model.pt", "d2a/policy.pt"):
        assert (tmp_path / name).stat().st_size > 0
