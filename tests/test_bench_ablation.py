"""The ablation bench: its changes touch only what they name, and its table pools seeds."""

from __future__ import annotations

import json

import pytest

from benchmarks.ablation import CHANGES, AblationConfig, run, table
from d2a_agents.policy.train import POLICY_PRESETS, TrainPolicyConfig


def test_each_change_alters_the_cpu_preset_where_it_says():
    base = TrainPolicyConfig(data="d", out="o")
    assert CHANGES["none"](base) == base
    assert CHANGES["adaptive-power-1"](base).policy.adaptive_power == 1.0
    assert CHANGES["no-projection-layernorm"](base).policy.encoder.project_norm is False
    assert CHANGES["batch-32"](base).batch_size == 32 and CHANGES["batch-32"](base).steps == base.steps
    previous = CHANGES["previous-preset"](base)
    assert (previous.policy.num_points, previous.batch_size, previous.policy.normalize_clouds) == (256, 32, False)
    assert POLICY_PRESETS["cpu"].policy.num_points == 64  # the preset itself is untouched
    with pytest.raises(ValueError, match="unknown change"):
        run(AblationConfig(data="d", task="hammer", change="more-magic"))


def test_table_pools_seeds_with_a_wilson_interval(tmp_path):
    check = {"intact": 0.01, "clouds_shuffled": 0.04, "state_shuffled": 0.5}
    for seed, wins in ((0, 9), (1, 10)):
        figures = {"task": "hammer", "change": "none", "algo": "mp1", "seed": seed, "wins": wins, "episodes": 10,
                   "train_seconds": 60.0, "reliance": check}
        (tmp_path / f"hammer_none_mp1_s{seed}.json").write_text(json.dumps(figures))
    row = table(str(tmp_path)).splitlines()[-1]
    # 19 of 20: Wilson 95 % interval 76.4-99.1 %
    assert row == "| hammer | none | mp1 | 2 | 95 [76-99] | 90 / 100 | 4.0 / 4.0 | 50.0 / 50.0 | 1.0 / 1.0 |"
