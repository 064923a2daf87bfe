"""`d2a bench train` at tiny sizes: a row per (preset, algo), an image policy on its own batch."""

from __future__ import annotations

from benchmarks.train import TrainBenchConfig, run
from d2a_agents.policy.agent import PolicyConfig
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.train import PolicyPreset


def test_bench_train_times_cloud_and_image_policies(capsys):
    tiny = PolicyPreset(PolicyConfig(num_points=16, encoder=EncoderConfig(point_widths=(8,), image_widths=(4, 4, 4, 4)),
                                     network=VelocityNetConfig(hidden=16, layers=1)),
                        steps=1, batch_size=8, learning_rate=1e-3, image_batch_size=2)
    rows = run(TrainBenchConfig(rows=(("tiny", tiny, "mp1"), ("tiny", tiny, "dp")), steps=2, episodes=1,
                                episode_length=10, rgb_image_size=40))
    assert [(row["algo"], row["batch"]) for row in rows] == [("mp1", 8), ("dp", 2)]
    assert all(row["samples_per_s"] > 0 for row in rows)
    assert "| tiny | dp | 16 | 2 |" in capsys.readouterr().out
