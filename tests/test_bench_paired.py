"""The paired comparison: which cells pair, and its intervals against published and hand computations."""

from __future__ import annotations

import dataclasses
import json
import math

import pytest

from benchmarks import table4
from benchmarks.cells import DEFAULT_DEMOS, Cell
from benchmarks.ordering import OrderingConfig, common_cells, plot, rank, steps
from benchmarks.paired import (
    PairedConfig,
    cell_files,
    find_pairs,
    grid_note,
    holm_adjusted,
    newcombe_interval,
    pair_cells,
    paired_t_p_value,
    pairs_in,
    report,
    setting_name,
    signed_points,
    summarize_pairs,
)
from d2a.cli import main
from d2a_agents.checkpoint import save_checkpoint


def _write(directory, name: str, wins: int, episodes: int = 100, reliance: dict | None = None,
           demos: int = DEFAULT_DEMOS) -> None:
    task, algo, rest = name.split("_", 2)
    cell = Cell(task, algo, int(rest.split("_")[0][1:]), [wins / episodes], wins, episodes, train_seconds=1.0,
                reliance=reliance, demos=demos)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / f"{name}.json").write_text(json.dumps(dataclasses.asdict(cell)))


@pytest.mark.parametrize("a, n_a, b, n_b, expected", [
    # Newcombe (1998), Statistics in Medicine 17: 873-890, Table II, method 10.
    (56, 70, 48, 80, (0.0524, 0.3339)),
    (9, 10, 3, 10, (0.1705, 0.8090)),
    (10, 10, 0, 20, (0.6791, 1.0000)),
])
def test_newcombe_interval_matches_the_published_examples(a, n_a, b, n_b, expected):
    low, high = newcombe_interval(a, n_a, b, n_b)
    assert (round(low, 4), round(high, 4)) == expected


def test_only_cells_of_the_same_task_seed_and_settings_pair(tmp_path):
    cells = tmp_path / "grid" / "cells"
    _write(cells, "push_d2a_s0_e5_fresh_d5", 70)
    _write(cells, "push_d2a-present_s0_e5_fresh_d5", 60)
    _write(cells, "push_d2a_s1_e5_fresh_d5", 80)  # no control on seed 1
    _write(cells, "push_d2a-present_s1_e5_fresh_d5_num_points128", 50)  # another budget
    _write(cells, "push_mp1_s0_e5_fresh_d5", 90)  # another method
    _write(cells, "stick-pull_d2a-present_s0_e5_fresh_d5", 40)  # another task
    pairs = find_pairs(cell_files(tmp_path / "grid"), "d2a", "d2a-present")
    assert [(pair.name, pair.treated.final_wins, pair.control.final_wins) for pair in pairs] == \
        [("push_s0_e5_fresh_d5", 70, 60)]
    assert cell_files(cells) == cell_files(tmp_path / "grid")  # the report's directory or its cells/


def test_a_pair_copied_into_another_grid_counts_once(tmp_path):
    for grid in ("table1", "table4"):  # the control copied between the grids (--shared-cells)
        _write(tmp_path / grid, "push_d2a-present_s0_e5", 60)
        _write(tmp_path / grid, "push_mp1_s0_e5", 55)
    _write(tmp_path / "table1", "push_d2a_s0_e5", 70)  # each grid's own world model: two treated cells
    _write(tmp_path / "table4", "push_d2a_s0_e5", 64)
    grids = (str(tmp_path / "table1"), str(tmp_path / "table4"))
    assert [pair.treated.final_wins for pair in pairs_in(grids, "d2a", "d2a-present")] == [70, 64]
    assert len(pairs_in(grids, "d2a-present", "mp1")) == 1
    assert pairs_in(grids, "d2a-present", "mp1", tasks=("stick-pull",)) == []


def test_each_side_s_reliance_on_its_second_cloud_comes_from_its_run_s_checkpoint(tmp_path):
    def check(imagined: float) -> dict:
        return {"step": 4000, "where": "training", "windows": 8, "intact": 0.1, "clouds_shuffled": 1.0,
                "state_shuffled": 0.5, "imagined_shuffled": 0.1 * imagined}

    # (d2a wins, its ratio; control wins, its ratio): differences -5, +10, +15 rise with d2a's ratios 2, 4, 8
    sides = [(55, 2, 60, 1.5), (70, 4, 60, 3), (75, 8, 60, 1)]
    for seed, (wins, ratio, control_wins, control_ratio) in enumerate(sides):
        for algo, won, times in (("d2a", wins, ratio), ("d2a-present", control_wins, control_ratio)):
            _write(tmp_path / "grid", f"push_{algo}_s{seed}_e5", won)
            save_checkpoint(tmp_path / "work" / "runs" / f"push_{algo}_s{seed}_e5" / "policy.pt", "policy",
                            {"reliance": [check(times)]})
    _write(tmp_path / "grid", "push_d2a_s3_e5", 50)  # a pair whose runs are not at hand
    _write(tmp_path / "grid", "push_d2a-present_s3_e5", 50)
    config = PairedConfig(results=(str(tmp_path / "grid"),), runs=(str(tmp_path / "elsewhere"), str(tmp_path / "work")))
    text = report(pairs_in(config.results, "d2a", "d2a-present"), config)
    assert "| push_s1_e5 | 70/100 | 60/100 | +10 | 4.0 | 3.0 |" in text
    assert "| push_s3_e5 | 50/100 | 50/100 | +0 | - | - |" in text
    assert "over the 3 pairs with both checkpoints: `d2a` median x4.0, `d2a-present` median x1.5" in text
    assert "Spearman's rho between `d2a`'s reliance and its difference from `d2a-present`: +1.00" in text


def test_a_cell_s_own_perception_check_is_read_before_any_run_s(tmp_path):
    check = {"step": 4000, "where": "training", "windows": 8, "intact": 0.1, "clouds_shuffled": 1.0,
             "state_shuffled": 0.5}
    for algo, wins, imagined in (("d2a", 70, 0.6), ("d2a-present", 60, 0.2)):
        _write(tmp_path / "grid", f"push_{algo}_s0_e5", wins, reliance={**check, "imagined_shuffled": imagined})
    save_checkpoint(tmp_path / "work" / "runs" / "push_d2a_s0_e5" / "policy.pt", "policy",
                    {"reliance": [{**check, "imagined_shuffled": 9.0}]})  # the cell's own check wins
    row = "| push_s0_e5 | 70/100 | 60/100 | +10 | 6.0 | 2.0 |"
    for config in (PairedConfig(results=(str(tmp_path / "grid"),), runs=(str(tmp_path / "work"),)),
                   PairedConfig(results=(str(tmp_path / "grid"),))):  # with the runs at hand and without
        assert row in report(pairs_in(config.results, "d2a", "d2a-present"), config)


def test_summary_over_pairs_against_a_hand_computation(tmp_path):
    for seed, (treated, control) in enumerate([(70, 60), (50, 55), (90, 75)]):
        _write(tmp_path, f"push_d2a_s{seed}_e5", treated)
        _write(tmp_path, f"push_d2a-present_s{seed}_e5", control)
    summary = summarize_pairs(find_pairs(cell_files(tmp_path), "d2a", "d2a-present"))
    # Differences 0.10, -0.05, 0.15: mean 0.0667, sample sd 0.1041; t(0.975, 2 df) = 4.3027.
    half = 4.302652729911275 * math.sqrt(((0.1 - 0.2 / 3) ** 2 + (-0.05 - 0.2 / 3) ** 2 + (0.15 - 0.2 / 3) ** 2) / 2) \
        / math.sqrt(3)
    assert (summary.pairs, summary.wins, summary.ties, summary.losses) == (3, 2, 0, 1)
    assert summary.mean == pytest.approx(0.2 / 3)
    assert (summary.low, summary.high) == pytest.approx((0.2 / 3 - half, 0.2 / 3 + half))
    assert (summary.pooled_treated, summary.pooled_control) == pytest.approx((210 / 300, 190 / 300))
    assert (summary.pooled_low, summary.pooled_high) == pytest.approx(newcombe_interval(210, 300, 190, 300))
    # Wilson intervals by the textbook formula (z = 1.96): 210/300 [64.59-74.91], 190/300 [57.74-68.59].
    assert summary.treated_interval == pytest.approx((0.6459, 0.7491), abs=1e-4)
    assert summary.control_interval == pytest.approx((0.5774, 0.6859), abs=1e-4)
    assert not summary.intervals_apart


def test_holm_adjustment_against_a_hand_computation():
    # Sorted: 0.005 x 4 = 0.02, 0.01 x 3 = 0.03, 0.03 x 2 = 0.06, 0.04 x 1 = 0.04 -> kept at 0.06.
    assert holm_adjusted([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert holm_adjusted([0.3, math.nan, 0.2]) == pytest.approx([0.6, 1.0, 0.6])  # 0.2 x 3, 0.3 x 2, nan as 1
    assert holm_adjusted([0.04]) == [0.04] and holm_adjusted([]) == []


def test_paired_t_p_value_agrees_with_scipys_one_sample_test():
    from scipy.stats import ttest_1samp

    differences = [0.08, 0.13, 0.03, 0.08, 0.10]
    assert paired_t_p_value(differences) == pytest.approx(ttest_1samp(differences, 0.0).pvalue)
    assert paired_t_p_value([0.2, -0.1, 0.05]) == pytest.approx(ttest_1samp([0.2, -0.1, 0.05], 0.0).pvalue)
    assert math.isnan(paired_t_p_value([0.1])) and math.isnan(paired_t_p_value([0.0, 0.0, 0.0]))


def test_each_setting_with_two_pairs_is_tested_and_adjusted_for_the_others(tmp_path):
    assert setting_name("push_s12_e5_fresh_d2_num_points128") == "push_e5_fresh_d2_num_points128"
    assert setting_name("stick-pull_s0") == "stick-pull"
    assert (signed_points(-1e-17), signed_points(0.084), signed_points(-0.0333)) == ("+0.0", "+8.4", "-3.3")
    for seed, (treated, control) in enumerate([(30, 20), (25, 12), (33, 30)]):  # differences +10, +13, +3
        _write(tmp_path, f"push_d2a_s{seed}_e5_fresh_d2", treated)
        _write(tmp_path, f"push_d2a-present_s{seed}_e5_fresh_d2", control)
    for seed, (treated, control) in enumerate([(80, 90), (70, 60)]):  # -10, +10: no lead
        _write(tmp_path, f"stick-pull_d2a_s{seed}_e5_fresh_d5", treated)
        _write(tmp_path, f"stick-pull_d2a-present_s{seed}_e5_fresh_d5", control)
    _write(tmp_path, "hammer_d2a_s0_e5", 99)  # one pair: not tested on its own
    _write(tmp_path, "hammer_d2a-present_s0_e5", 98)
    pairs = find_pairs(cell_files(tmp_path), "d2a", "d2a-present")
    text = report(pairs, PairedConfig(results=(str(tmp_path),), reference=None))
    assert "the 2 settings with two pairs or more" in text and "| hammer_e5 |" not in text
    rows = text.split("Per setting")[1].splitlines()[4:]
    # Push: differences 0.10, 0.13, 0.03: mean 0.0867, sd 0.0513, t = 2.925 on 2 df, whose two-sided
    # p is 1 - t / sqrt(t^2 + 2) = 0.0997; half-width 4.3027 x 0.0296 = 0.1275. Stick-Pull: t = 0, p = 1;
    # half-width 12.706 x 0.1. Holm over the two: 0.0997 x 2, then 1.
    t = 0.26 / 3 / (math.sqrt(0.0052667 / 2) / math.sqrt(3))
    assert 1 - t / math.sqrt(t * t + 2) == pytest.approx(0.0997, abs=1e-4)
    assert rows == ["| push_e5_fresh_d2 | 3 | 3 / 0 / 0 | +8.7 [-4.1, +21.4] | 0.100 | 0.199 |",
                    "| stick-pull_e5_fresh_d5 | 2 | 1 / 0 / 1 | +0.0 [-127.1, +127.1] | 1.000 | 1.000 |"]
    # one setting alone (a replication): its p in one sentence, two-sided and halved, nothing to adjust
    alone = report([pair for pair in pairs if pair.treated.task == "push"],
                   PairedConfig(results=(str(tmp_path),), reference=None))
    assert "Per setting" not in alone
    assert ("One setting with two pairs or more (push_e5_fresh_d2, 3 pairs): Student's paired t test of a zero "
            "mean difference, two-sided p = 0.100, one-sided in the direction of its mean p = 0.050.") in alone
    hammer = report([pair for pair in pairs if pair.treated.task == "hammer"],
                    PairedConfig(results=(str(tmp_path),), reference=None))
    assert "One setting" not in hammer and "Per setting" not in hammer  # one pair: nothing to test


def test_pooled_intervals_apart_only_when_they_share_no_point(tmp_path):
    _write(tmp_path, "push_d2a_s0_e5", 70)
    _write(tmp_path, "push_d2a-present_s0_e5", 50)  # Wilson [60.4-78.1] against [40.4-59.6]
    _write(tmp_path, "push_mp1_s0_e5", 60)  # [50.2-69.1]: overlaps 70's
    assert summarize_pairs(find_pairs(cell_files(tmp_path), "d2a", "d2a-present")).intervals_apart
    assert summarize_pairs(find_pairs(cell_files(tmp_path), "mp1", "d2a-present")).intervals_apart is False
    assert summarize_pairs(find_pairs(cell_files(tmp_path), "d2a", "mp1")).intervals_apart is False


def test_cli_prints_the_pairs_and_draws_them(tmp_path, capsys):
    _write(tmp_path / "a", "push_d2a_s0_e5", 70)
    _write(tmp_path / "a", "push_d2a-present_s0_e5", 60)
    _write(tmp_path / "b", "push_d2a-present_s0_e5", 10)  # a twin only in another directory: no pair
    main(["bench", "paired", "--results", str(tmp_path / "a"), "--results", str(tmp_path / "b"),
          "--plot", str(tmp_path / "paired.png")])
    out = capsys.readouterr().out
    assert "| push_s0_e5 | 70/100 | 60/100 | +10 |" in out and "1 pair of" in out
    assert (tmp_path / "paired.png").stat().st_size > 0
    with pytest.raises(SystemExit, match="has a mp1 twin"):
        main(["bench", "paired", "--results", str(tmp_path / "a"), "--control", "mp1"])
    with pytest.raises(SystemExit, match="no directory of cells"):
        main(["bench", "paired", "--results", str(tmp_path / "missing")])
    with pytest.raises(ValueError, match="nothing to compare"):
        PairedConfig(results=(str(tmp_path),), algo="mp1", control="mp1")


def test_pairs_can_be_kept_to_some_tasks(tmp_path, capsys):
    for task, wins in (("push", 70), ("adroit-door", 20)):
        _write(tmp_path, f"{task}_d2a_s0_e5", wins)
        _write(tmp_path, f"{task}_d2a-present_s0_e5", 50)
    main(["bench", "paired", "--results", str(tmp_path), "--task", "adroit-door"])
    out = capsys.readouterr().out
    assert "| adroit-door_s0_e5 | 20/100 | 50/100 | -30 |" in out and "push_s0" not in out and "1 pair of" in out
    with pytest.raises(SystemExit, match="no d2a cell of reach"):
        main(["bench", "paired", "--results", str(tmp_path), "--task", "reach"])


def test_pairs_can_be_kept_to_some_demonstration_counts(tmp_path, capsys):
    for demos, wins in ((1, 12), (2, 30), (DEFAULT_DEMOS, 90)):
        tag = "" if demos == DEFAULT_DEMOS else f"_d{demos}"
        _write(tmp_path, f"push_d2a_s0_e5{tag}", wins, demos=demos)
        _write(tmp_path, f"push_d2a-present_s0_e5{tag}", 20, demos=demos)
    main(["bench", "paired", "--results", str(tmp_path), "--demos", "1", "--demos", "2"])
    out = capsys.readouterr().out
    assert "| push_s0_e5_d1 | 12/100 | 20/100 | -8 |" in out and "| push_s0_e5_d2 | 30/100 | 20/100 | +10 |" in out
    assert "2 pairs of" in out and "push_s0_e5 |" not in out
    with pytest.raises(SystemExit, match="no d2a cell at 5 demonstrations"):
        main(["bench", "paired", "--results", str(tmp_path), "--demos", "5"])


def test_a_grid_report_closes_with_its_pairs():
    def cell(algo: str, seed: int, demos: int, wins: int) -> Cell:
        return Cell("push", algo, seed, [wins / 100], wins, 100, train_seconds=1.0, demos=demos)

    cells = [cell("d2a", 0, 5, 70), cell("d2a-present", 0, 5, 60), cell("d2a", 1, 5, 80),  # seed 1: no control
             cell("d2a-present", 0, 10, 90), cell("mp1", 0, 5, 50)]  # another count, another method
    pairs = pair_cells(cells, "d2a", "d2a-present")
    assert [(pair.name, pair.difference) for pair in pairs] == [("push_d5_s0", pytest.approx(0.1))]
    text = table4.report(cells, table4.Table4Config())
    assert text.endswith("1 pair of `d2a` and `d2a-present`: `d2a` ahead in 1, level in 0, behind in 0; mean "
                         "difference +10.0 points (one pair: no interval); pooled episodes 70.0 % [60.4-78.1] "
                         "against 60.0 % [50.2-69.1] (Wilson, overlapping), difference +10.0 [-3.2, +22.7] "
                         "(Newcombe).")
    assert grid_note([cell("mp1", 0, 5, 50)]) == []  # no pair, no note


def test_the_reference_method_stands_beside_each_pair_and_is_compared_over_those_that_have_it(tmp_path, capsys):
    for seed, (treated, control, reference) in enumerate([(70, 60, 50), (80, 85, None)]):
        _write(tmp_path, f"push_d2a_s{seed}_e5", treated)
        _write(tmp_path, f"push_d2a-present_s{seed}_e5", control)
        if reference is not None:
            _write(tmp_path, f"push_mp1_s{seed}_e5", reference)
    report_file = tmp_path / "report" / "paired.md"
    report_file.parent.mkdir()
    main(["bench", "paired", "--results", str(tmp_path), "--markdown", str(report_file)])
    out = capsys.readouterr().out
    assert "| cell | `d2a` | `d2a-present` | difference (points) | `mp1` |" in out
    assert "| push_s0_e5 | 70/100 | 60/100 | +10 | 50/100 |" in out
    assert "| push_s1_e5 | 80/100 | 85/100 | -5 | - |" in out
    # Only seed 0 has an mp1 cell: 70/100 against 50/100, +20 points, Newcombe's interval around it.
    low, high = newcombe_interval(70, 100, 50, 100)
    assert (f"Against `mp1` on the pairs with its cell: 1 pair of `d2a` and `mp1`: `d2a` ahead in 1, level in 0, "
            f"behind in 0; mean difference +20.0 points (one pair: no interval); pooled episodes 70.0 % [60.4-78.1] "
            f"against 50.0 % [40.4-59.6] (Wilson, apart), difference +20.0 [{100 * low:+.1f}, {100 * high:+.1f}] "
            f"(Newcombe).") in out
    page = report_file.read_text()
    assert page.startswith("# `d2a` against `d2a-present`, cell by cell")
    assert f"Written by `d2a bench paired --results {tmp_path} --algo d2a --control d2a-present --reference mp1 " \
           f"--markdown {report_file}`." in page and "| push_s0_e5 | 70/100 | 60/100 | +10 | 50/100 |" in page
    main(["bench", "paired", "--results", str(tmp_path), "--control", "mp1"])  # the reference is a side: no column
    out = capsys.readouterr().out
    assert "| push_s0_e5 | 70/100 | 50/100 | +20 |" in out and "Against" not in out


def test_each_step_of_a_ranking_gets_its_verdict_from_a_hand_computed_interval(tmp_path, capsys):
    wins = {"dp": [10, 20, 30], "cp": [50, 60, 70], "mp1": [40, 70, 60], "dp3": [20, 45, 30]}
    for method, per_seed in wins.items():
        for seed, won in enumerate(per_seed):
            _write(tmp_path, f"push_{method}_s{seed}_e5", won)
    _write(tmp_path, "stick-pull_dp_s0_e5", 10)  # only dp and cp have Stick-Pull
    _write(tmp_path, "stick-pull_cp_s0_e5", 60)
    config = OrderingConfig(results=(str(tmp_path),), order=("dp", "cp", "mp1", "dp3"))
    found = {(step.lower, step.higher): step for step in steps(config)}
    # dp < cp: +40, +40, +40, +50 -> mean 42.5, sd 5, t(0.975, 3) = 3.1824 -> [34.5, 50.5]: holds.
    rising = found["dp", "cp"].summary
    assert rising.pairs == 4 and rising.mean == pytest.approx(0.425)
    assert (rising.low, rising.high) == pytest.approx((0.425 - 3.182446305284263 * 0.05 / 2,
                                                       0.425 + 3.182446305284263 * 0.05 / 2))
    assert found["dp", "cp"].verdict == "holds"
    # cp < mp1: -10, +10, -10 -> the interval spans zero.
    assert found["cp", "mp1"].verdict == "not separated"
    # mp1 < dp3: -20, -25, -30 -> mean -25, sd 5, t(0.975, 2) = 4.3027 -> [-37.4, -12.6]: reversed.
    falling = found["mp1", "dp3"].summary
    assert falling.high == pytest.approx(-0.25 + 4.302652729911275 * 0.05 / math.sqrt(3))
    assert found["mp1", "dp3"].verdict == "reversed"
    common = common_cells(config)
    assert [len(cells) for cells in common.values()] == [3, 3, 3, 3]  # Stick-Pull is not common to all
    assert sum(cell.final_wins for cell in common["dp"]) == 60
    assert plot(rank(config), tmp_path / "order.png").stat().st_size > 0
    with pytest.raises(ValueError, match="no cell is shared"):
        plot(rank(OrderingConfig(results=(str(tmp_path),), order=("dp", "flowpolicy"))), tmp_path / "none.png")

    main(["bench", "order", "--results", str(tmp_path), "--order", "dp", "flowpolicy"])
    out = capsys.readouterr().out
    assert "No cell is shared by every method" in out and "| `dp` < `flowpolicy` | 0 |" in out
    assert out.rstrip().endswith("no shared cell |")
