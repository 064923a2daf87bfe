"""`d2a bench latency` end to end at tiny sizes: every row is timed, a trained world model
is timed on its demonstrations, and a world model without demonstrations is refused."""

from __future__ import annotations

import pytest

from benchmarks.latency import LatencyBenchConfig, run
from d2a_agents.world_model.train import TrainWorldModelConfig, train_world_model
from d2a_agents.world_model.triplane import WorldModelConfig


def test_bench_latency_times_policies_and_world_models(reach_data, tmp_path, capsys):
    world_model = tmp_path / "wm.pt"
    train_world_model(TrainWorldModelConfig(
        data=reach_data, out=str(world_model), model=WorldModelConfig(resolution=(16, 16, 8), channels=4), steps=1,
        batch_size=2, queries=64, validate_every=1, validation_stride=50, progress=False))
    results = run(LatencyBenchConfig(task="reach", num_points=64, repeats=2, rgb_image_size=40,
                                     world_models=(WorldModelConfig(resolution=(8, 8, 4), channels=4),),
                                     world_model=str(world_model), data=reach_data))
    expected = {"d2a", "mp1", "dp3", "flowpolicy", "edm", "cp", "dp", "d2a cpu preset", "dp cpu preset",
                "imagination 8x8x4, untrained, whole band"}
    assert expected <= set(results)
    trained = [name for name in results if "trained (wm.pt)" in name]
    assert len(trained) == 4  # the data's cloud size and the policy's point count, whole band and grown
    assert all(seconds > 0 for seconds in results.values())
    assert "D2A policy, cpu preset" in capsys.readouterr().out


def test_a_trained_world_model_needs_its_demonstrations():
    with pytest.raises(ValueError, match="both world_model and data"):
        LatencyBenchConfig(world_model="wm.pt")
