"""``d2a report``: runs grouped over seeds, pooled success with a Wilson interval computed here
independently (scipy), reliance ratios, and the settings that tell rows apart."""

from __future__ import annotations

import pytest
from matplotlib.image import imread
from scipy.stats import binomtest

from d2a.cli import main
from d2a_agents.checkpoint import save_checkpoint
from d2a_agents.policy.report import format_report, read_run, report_bars, report_rows
from d2a_agents.success_plot import SuccessBar, plot_success_bars


def fake_run(path, seed: int, wins: int, shift: float, algo: str = "mp1", final: bool = True, steps: int = 10) -> None:
    """A policy checkpoint as train-policy writes it, minus the networks (the report reads no weights);
    ``steps``: the run's planned length (10: finished)."""
    history = [{"step": 5, "success_rate": 0.1, "episodes": 20, "task": "push"}]
    if final:
        history.append({"step": 10, "success_rate": wins / 100, "episodes": 100, "task": "push"})
    save_checkpoint(path / "policy.pt", "policy", {
        "policy_config": {"algo": algo, "num_points": 64, "encoder": {"widths": (32, 64)}},
        "run_config": {"data": "data/push", "batch_size": 256, "augment_shift": None, "seed": seed},
        "train_config": {"steps": steps}, "augment_shift": shift, "step": 10, "history": history,
        "reliance": [{"step": 10, "where": "training", "windows": 512, "intact": 0.01, "clouds_shuffled": 0.25,
                      "state_shuffled": 0.5, "imagined_shuffled": None}],
    })


def test_seeds_of_one_setting_pool_into_one_row(tmp_path):
    fake_run(tmp_path / "a0", seed=0, wins=90, shift=0.02)
    fake_run(tmp_path / "a1", seed=1, wins=80, shift=0.02)
    fake_run(tmp_path / "b0", seed=0, wins=70, shift=0.0)
    rows = report_rows([outcome for run in ("a1", "a0", "b0") for outcome in read_run(tmp_path / run)])
    assert [(row.differs, [run.seed for run in row.runs]) for row in rows] == [
        ("augment_shift=0.0", [0]), ("augment_shift=0.02", [0, 1])]
    rate, low, high = rows[1].pooled
    interval = binomtest(170, 200).proportion_ci(method="wilson")
    assert rate == pytest.approx(0.85) and (low, high) == pytest.approx((interval.low, interval.high))
    assert rows[1].runs[0].reliance == pytest.approx({"clouds": 25.0, "state": 50.0})
    table = format_report(rows)
    assert "| push | mp1 | augment_shift=0.02 | 0 / 1 | 90 / 80 (of 100) | 85.0 [" in table
    assert "| 25.0 / 25.0 | - / - | 50.0 / 50.0 |" in table


def test_unevaluated_runs_and_repeated_seeds(tmp_path, capsys):
    fake_run(tmp_path / "running", seed=0, wins=0, shift=0.02, final=False)  # evaluated at step 5, not at 10
    assert read_run(tmp_path / "running") == []
    fake_run(tmp_path / "midway", seed=0, wins=50, shift=0.02, steps=20)  # evaluated at 10 of its 20 steps
    assert read_run(tmp_path / "midway") == []
    fake_run(tmp_path / "a", seed=0, wins=90, shift=0.02)
    fake_run(tmp_path / "again", seed=0, wins=91, shift=0.02)
    with pytest.raises(ValueError, match="same settings and seed"):
        report_rows(read_run(tmp_path / "a") + read_run(tmp_path / "again"))
    save_checkpoint(tmp_path / "wm.pt", "world_model", {})
    main(["report", str(tmp_path / "a"), str(tmp_path / "running"), str(tmp_path / "wm.pt")])
    captured = capsys.readouterr()
    assert "| push | mp1 | - | 0 | 90 (of 100) |" in captured.out
    assert "running: still training, or not evaluated" in captured.err and "not a policy" in captured.err
    with pytest.raises(SystemExit, match="no evaluated run"):
        main(["report", str(tmp_path / "running")])


def test_rows_become_bars_per_task_with_seeds(tmp_path):
    fake_run(tmp_path / "a0", seed=0, wins=90, shift=0.02)
    fake_run(tmp_path / "a1", seed=1, wins=80, shift=0.02)
    fake_run(tmp_path / "b0", seed=0, wins=70, shift=0.0)
    fake_run(tmp_path / "d0", seed=0, wins=60, shift=0.02, algo="dp3")
    rows = report_rows([outcome for run in ("a0", "a1", "b0", "d0") for outcome in read_run(tmp_path / run)])
    bars = report_bars(rows)
    assert set(bars) == {"mp1 (augment_shift=0.02)", "mp1 (augment_shift=0.0)", "dp3"}
    pooled = bars["mp1 (augment_shift=0.02)"]["push"]
    interval = binomtest(170, 200).proportion_ci(method="wilson")
    assert (pooled.rate, pooled.low, pooled.high) == pytest.approx((0.85, interval.low, interval.high))
    assert pooled.seeds == pytest.approx((0.9, 0.8)) and pooled.marker is None
    main(["report", *(str(tmp_path / run) for run in ("a0", "a1", "d0")), "--plot", str(tmp_path / "bars.png")])
    assert imread(tmp_path / "bars.png").ndim == 3  # a real image, decodable


def test_a_variant_missing_a_task_leaves_a_gap_and_an_empty_plot_is_refused(tmp_path):
    bars = {"mp1": {"push": SuccessBar(0.5, 0.4, 0.6), "hammer": SuccessBar(1.0, 0.96, 1.0, marker=0.98)},
            "d2a": {"hammer": SuccessBar(0.9, 0.8, 0.95, seeds=(0.9,))}}
    assert imread(plot_success_bars(bars, tmp_path / "gap.png", "t")).ndim == 3
    with pytest.raises(ValueError, match="nothing to plot"):
        plot_success_bars({}, tmp_path / "none.png", "t")
