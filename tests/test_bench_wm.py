"""``d2a bench wm`` on tiny settings: every (horizon, model) row, the Chamfer references, the table."""

from __future__ import annotations

import shutil

from benchmarks.world_model import BenchModel, WorldModelBenchConfig, run
from d2a_agents.world_model.triplane import WorldModelConfig

TINY = dict(channels=4, refine_dilations=(1,), pe_frequencies=2, decoder_hidden=16, decoder_layers=2)


def test_bench_trains_each_model_at_each_horizon_and_prints_one_row_each(reach_data, tmp_path, capsys):
    shutil.copytree(reach_data, tmp_path / "data" / "reach")  # the bench reuses a data set it finds
    models = (
        BenchModel("scatter", WorldModelConfig(resolution=(16, 16, 4), encoder="point-scatter", **TINY), 2),
        BenchModel("conv", WorldModelConfig(resolution=(8, 8, 4), **TINY), 3),
    )
    config = WorldModelBenchConfig(tasks=("reach",), workdir=str(tmp_path), models=models, horizons=(1, 3),
                                   queries=64, latency_steps=2, chamfer_stride=40)
    rows = run(config)

    assert [(row["label"], row["horizon"], row["steps"]) for row in rows] == [
        ("scatter", 1, 2), ("conv", 1, 3), ("scatter", 3, 2), ("conv", 3, 3)]
    assert len({row["params"] for row in rows}) == 2  # the two models differ; H does not change the size
    for row in rows:
        assert 0 <= row["dynamic"] <= 1 and 0 <= row["full"] <= 1 and 0 < row["persistence"] <= 1
        assert set(row["chamfer"]) == {"imagined", "centres", "persistence", "oracle"}
        assert all(0 <= value < 1 for value in row["chamfer"].values())  # metres, inside a 1-m workspace
    assert len(list((tmp_path / "models").glob("reach_*.pt"))) == 4
    table = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| reach |")]
    # two latencies (the env's cloud size / the policy's points) and four Chamfer figures per row
    assert len(table) == 4 and all(line.count("/") == 1 + 3 for line in table)
    assert all(0 < row["policy_latency"] for row in rows)
