"""The Table I bench: its order, its per-group figures against hand computations, its files,
and two processes sharing one grid."""

from __future__ import annotations

import csv
import dataclasses
import io
import math

import pytest

import benchmarks.success as success
from benchmarks.cells import Cell, progress_line
from benchmarks.success import SuccessBenchConfig
from benchmarks.table1 import Table1Config, group_tasks, paired_by_group, plan, report, run, task_csv
from collectors.atomic import exclusive_writer
from d2a.cli import main

VERY_HARD = ["disassemble", "pick-place-wall", "shelf-place", "stick-pull", "stick-push"]


def _cell(task: str, algo: str, seed: int, wins: int, periodic: list[float] | None = None) -> Cell:
    return Cell(task, algo, seed, periodic or [wins / 100], wins, 100, train_seconds=600.0, final_seconds=300.0)


def _wilson(wins: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    p = wins / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def test_plan_runs_group_by_group_then_seed_by_seed():
    config = Table1Config(groups=("very_hard", "easy"), algos=("mp1", "dp3"), seeds=(0, 1))
    cells = plan(config)
    assert sorted(group_tasks("very_hard")) == VERY_HARD
    assert len(cells) == (5 + 21) * 2 * 2
    assert cells[:10] == [(task, algo, 0) for task in group_tasks("very_hard") for algo in ("mp1", "dp3")]
    assert {seed for _, _, seed in cells[10:20]} == {1}
    assert cells[20] == (group_tasks("easy")[0], "mp1", 0)


def test_report_gives_group_means_over_complete_seeds():
    tasks = group_tasks("very_hard")
    cells = [_cell(task, "mp1", 0, wins) for task, wins in zip(tasks, (10, 20, 30, 40, 50), strict=True)]
    cells += [_cell(task, "mp1", 1, wins) for task, wins in zip(tasks, (20, 30, 40, 50, 60), strict=True)]
    cells.append(_cell(tasks[0], "mp1", 2, 90))  # seed 2 has one task only: not a complete seed
    cells += [_cell("assembly", "mp1", 0, 70), _cell("push", "mp1", 0, 80)]  # Hard: 2 of its 4 tasks
    text = report(cells, Table1Config(algos=("mp1",)))
    rows = {tuple(part.strip() for part in line.split("|")[1:3]): line.split("|")[3:-1]
            for line in text.splitlines() if line.startswith("| ")}
    easy, medium, hard, very_hard, *adroit = (entry.strip() for entry in rows["`mp1`", "honest"])
    # Seeds 0 and 1: group means 30 % and 40 %; sample std 7.07; their cells pooled: 350 wins of
    # 1000 episodes (seed 2's lone cell is left out of the interval as of the mean).
    low, high = _wilson(350, 1000)
    assert very_hard == f"35.0 ± 7.1 [{100 * low:.0f}-{100 * high:.0f}] (2 seeds)"
    assert hard == "75.0 over 2/4 tasks" and easy == medium == "-"
    assert adroit == ["-", "-", "-"]  # no Adroit cell yet
    # One periodic evaluation each: the paper protocol equals the honest figure here.
    assert rows["`mp1`", "paper"][3].strip() == "35.0 ± 7.1 (2 seeds)"
    paper_row = [entry.strip() for entry in rows["mp1 (paper)", "paper"]]
    assert paper_row == ["88.2", "68", "58.1", "67.2", "100", "69", "58"]
    assert "Adroit columns: per task" in text


def test_the_adroit_columns_run_last_at_their_own_settings():
    config = Table1Config(algos=("mp1",), seeds=(0,))
    grid = plan(config)
    assert [task for task, _, _ in grid[-3:]] == ["adroit-hammer", "adroit-door", "adroit-pen"]
    assert plan(Table1Config(groups=("adroit",), algos=("mp1", "dp3"), seeds=(0, 1)))[:2] == [
        ("adroit-hammer", "mp1", 0), ("adroit-hammer", "dp3", 0)]
    door, hammer, push = (config.task_cell_config(task) for task in ("adroit-door", "adroit-hammer", "push"))
    assert (door.dart_noise, hammer.dart_noise, push.dart_noise) == (0.05, 0.1, 0.0)
    assert door.env_kwargs == {"num_points": 512, "image_size": 84} and push.env_kwargs == config.bench.env_kwargs
    assert (door.policy.policy.num_points, door.action_draws, push.action_draws) == (256, 8, 1)
    assert door.policy.steps == push.policy.steps and door.cells == push.cells  # the budget and the cells' place
    assert success.cell_path(door, "adroit-door", "mp1", 0).name == (
        "adroit-door_mp1_s0_e5_fresh_dart0.05_draws8_num_points256.json")
    with pytest.raises(ValueError, match="unknown group"):
        Table1Config(groups=("adroit", "pen"))


def test_adroit_entries_are_per_task_means_over_seeds(tmp_path, capsys):
    config = Table1Config(groups=("adroit",), algos=("mp1",), seeds=(0, 1), results=str(tmp_path))
    for seed, wins in ((0, 40), (1, 50)):
        success._store(config.task_cell_config("adroit-door"), _cell("adroit-door", "mp1", seed, wins))
    success._store(config.task_cell_config("adroit-hammer"), _cell("adroit-hammer", "mp1", 0, 70))
    success._store(config.cell_config(), _cell("adroit-pen", "mp1", 0, 99))  # Meta-World's settings: not a Pen cell
    main(["bench", "table1", "--group", "adroit", "--algo", "mp1", "--results", str(tmp_path), "--report"])
    text = (tmp_path / "table1.md").read_text()
    honest = next(line for line in text.splitlines() if line.startswith("| `mp1` | honest"))
    *_, hammer, door, pen = (entry.strip() for entry in honest.split("|")[1:-1])
    low, high = _wilson(90, 200)
    assert door == f"45.0 ± 7.1 [{100 * low:.0f}-{100 * high:.0f}] (2 seeds)"
    low, high = _wilson(70, 100)
    assert hammer == f"70.0 ± 0.0 [{100 * low:.0f}-{100 * high:.0f}] (1 seed)" and pen == "-"
    assert "3 of 9 cells finished" in capsys.readouterr().out  # 3 tasks x 3 seeds (the default)
    rows = list(csv.DictReader(io.StringIO((tmp_path / "tasks.csv").read_text())))
    assert {row["group"] for row in rows} == {"adroit"} and len(rows) == 3
    assert (tmp_path / "table1.png").stat().st_size > 0  # Adroit cells alone are plotted


def test_task_csv_has_one_row_per_cell():
    checked = dataclasses.replace(_cell("push", "d2a", 1, 40), reliance={  # its last perception check
        "step": 4000, "where": "training", "windows": 512, "intact": 0.02, "clouds_shuffled": 0.5,
        "state_shuffled": 0.1, "imagined_shuffled": 0.07})
    cells = [_cell("push", "dp3", 1, 37, periodic=[0.2, 0.5, 0.4]), checked]
    unchecked, imagining = csv.DictReader(io.StringIO(task_csv(cells)))
    assert unchecked == {"task": "push", "algo": "dp3", "seed": "1", "demos": "10", "paper": "0.3667",
                         "honest": "0.3700", "final_wins": "37", "final_episodes": "100", "train_seconds": "600",
                         "final_seconds": "300", "clouds_shuffled_x": "", "second_cloud_shuffled_x": "",
                         "group": "hard"}
    assert (imagining["clouds_shuffled_x"], imagining["second_cloud_shuffled_x"]) == ("25.00", "3.50")  # 0.5 / 0.02


def test_progress_estimates_each_unfinished_cell_at_its_methods_rate():
    """dp3 cells took 0.25 h, the d2a cell 1 h: two d2a cells and one dp3 cost 2.25 h; mp1,
    with no finished cell, counts at the mean of all three (1.5 h / 3 = 0.5 h)."""
    slow = dataclasses.replace(_cell("push", "d2a", 0, 50), train_seconds=3000.0, final_seconds=600.0)
    cells = [_cell("push", "dp3", 0, 50), _cell("push", "dp3", 1, 50), slow]
    line = progress_line(cells, ["d2a", "dp3", "mp1", "d2a", "dp3", "dp3", "d2a"])  # 3 of them finished
    assert line.startswith("3 of 7 cells finished, 1.5 one-thread hours")
    assert "the other 4 at their method's mean rate: about 2.8 more" in line  # 2 x 1 + 0.25 + 0.5 = 2.75
    assert "(2 `d2a` x 1.00 h, 1 `dp3` x 0.25 h, 1 `mp1` x 0.50 h)" in line
    finished = progress_line(cells, ["dp3", "dp3", "d2a"])
    assert finished.startswith("3 of 3 cells finished, 1.5 one-thread hours") and "mean rate" not in finished


def test_pairs_are_summarised_group_by_group_against_the_control_and_mp1():
    cells = [_cell("disassemble", "d2a", 0, 70), _cell("disassemble", "d2a-present", 0, 60),
             _cell("disassemble", "mp1", 0, 80), _cell("stick-push", "d2a", 0, 50),
             _cell("stick-push", "d2a-present", 0, 50), _cell("button-press", "d2a", 0, 90),
             _cell("button-press", "mp1", 0, 100), _cell("push", "mp1", 0, 40)]  # Hard: no d2a, no line
    lines = [line for line in paired_by_group(cells) if line.startswith("- ")]
    assert [line.split(":")[0] for line in lines] == ["- Very Hard", "- Very Hard", "- Easy"]
    # Very Hard against the control: +10 and 0 points, mean +5; against mp1 one pair, -10.
    assert "2 pairs of `d2a` and `d2a-present`: `d2a` ahead in 1, level in 1, behind in 0; mean difference +5.0" \
        in lines[0]
    assert "1 pair of `d2a` and `mp1`: `d2a` ahead in 0, level in 0, behind in 1; mean difference -10.0" in lines[1]
    assert "1 pair of `d2a` and `mp1`" in lines[2]
    assert "pooled episodes 90.0 % [82.6-94.5] against 100.0 % [96.3-100.0]" in lines[2]
    assert paired_by_group([_cell("push", "mp1", 0, 40)]) == []


def test_report_only_writes_the_files_from_stored_cells(tmp_path, capsys):
    config = Table1Config(groups=("very_hard",), algos=("mp1",), seeds=(0,), results=str(tmp_path))
    for task in VERY_HARD[:4]:
        success._store(config.cell_config(), _cell(task, "mp1", 0, 50))
    main(["bench", "table1", "--group", "very_hard", "--algo", "mp1", "--seed", "0", "--results", str(tmp_path),
          "--report"])
    out = capsys.readouterr().out
    assert "4 of 5 cells finished, 1.0 one-thread hours" in out
    assert "the other 1 at their method's mean rate: about 0.2 more (1 `mp1` x 0.25 h)" in out
    assert "50.0 over 4/5 tasks" in (tmp_path / "table1.md").read_text()
    assert len((tmp_path / "tasks.csv").read_text().splitlines()) == 5
    assert not (tmp_path / "table1.png").exists()  # no complete seed to draw yet
    success._store(config.cell_config(), _cell(VERY_HARD[4], "mp1", 0, 50))
    run(config, report_only=True)
    assert (tmp_path / "table1.png").stat().st_size > 0


def test_a_run_of_one_group_and_method_reports_every_finished_cell(tmp_path):
    """Group-by-group runs share one report: a `d2a` run on Very Hard keeps the `mp1` rows and the
    Hard cells that other runs stored, and its progress line counts its own grid only."""
    config = Table1Config(groups=("very_hard",), algos=("d2a",), seeds=(0,), results=str(tmp_path))
    for task in VERY_HARD:
        success._store(config.cell_config(), _cell(task, "mp1", 0, 60))
    success._store(config.cell_config(), _cell("push", "mp1", 1, 70))
    success._store(config.cell_config(), _cell(VERY_HARD[0], "d2a", 0, 40))
    cells = run(config, report_only=True)
    assert [(cell.task, cell.algo) for cell in cells] == [(VERY_HARD[0], "d2a")]
    rows = {tuple(part.strip() for part in line.split("|")[1:3]): [entry.strip() for entry in line.split("|")[3:-1]]
            for line in (tmp_path / "table1.md").read_text().splitlines() if line.startswith("| `")}
    assert rows["`mp1`", "honest"][3].startswith("60.0 ± 0.0") and rows["`mp1`", "honest"][2] == "70.0 over 1/4 tasks"
    assert rows["`d2a`", "honest"][3] == "40.0 over 1/5 tasks"


def test_a_run_of_some_methods_and_seeds_writes_the_whole_grids_report(tmp_path):
    """The lanes of a grid run subsets of it: the files they write must not depend on which."""
    whole = Table1Config(groups=("very_hard",), results=str(tmp_path))
    for task, algo, seed in [(VERY_HARD[0], "mp1", 0), (VERY_HARD[0], "d2a", 0), (VERY_HARD[1], "dp3", 2),
                             (VERY_HARD[1], "mp1", 1), ("push", "d2a-present", 0)]:
        success._store(whole.cell_config(), _cell(task, algo, seed, 30 + seed))
    written = []
    for config in (whole, dataclasses.replace(whole, groups=("hard",), algos=("d2a-present", "d2a"), seeds=(2, 1))):
        run(config, report_only=True)
        written.append([(tmp_path / name).read_text() for name in ("table1.md", "tasks.csv", "tasks.md")])
    assert written[0] == written[1]
    assert len(written[0][1].splitlines()) == 6  # every stored cell, once


def test_a_cell_another_process_holds_is_skipped(tmp_path, monkeypatch):
    config = SuccessBenchConfig(tasks=("reach",), algos=("mp1",), seeds=(0, 1), workdir=str(tmp_path))
    trained = []
    monkeypatch.setattr(success, "_dataset", lambda config, task: tmp_path / "data" / task)
    monkeypatch.setattr(success, "run_cell", lambda config, task, algo, seed, data, world_model:
                        trained.append(seed) or _cell(task, algo, seed, 10))
    held = success.cell_path(config, "reach", "mp1", 0).stem
    with exclusive_writer(tmp_path / "runs", lock_name=f".{held}.lock"):  # another process trains seed 0
        cells = success.run_grid(config, [("reach", "mp1", 0), ("reach", "mp1", 1)])
    assert trained == [1] and [cell.seed for cell in cells] == [1]
    # Once the other process has stored seed 0, a rerun reads it back and trains nothing.
    success._store(config, _cell("reach", "mp1", 0, 20))
    cells = success.run_grid(config, [("reach", "mp1", 0), ("reach", "mp1", 1)])
    assert [cell.final_wins for cell in cells] == [20, 10]
    assert trained == [1]


def test_only_a_cell_that_imagines_builds_the_world_model(tmp_path, monkeypatch):
    """A process whose cell reads no world model trains it at once, while another writes the model."""
    config = SuccessBenchConfig(tasks=("reach",), algos=("mp1", "d2a", "d2a-present"), seeds=(0,),
                                workdir=str(tmp_path))
    events = []
    monkeypatch.setattr(success, "_dataset", lambda config, task: tmp_path / "data" / task)
    monkeypatch.setattr(success, "_world_model", lambda config, task, data: events.append("world model") or
                        tmp_path / "wm.pt")
    monkeypatch.setattr(success, "run_cell", lambda config, task, algo, seed, data, world_model:
                        events.append((algo, world_model)) or _cell(task, algo, seed, 10))
    success.run_grid(config, [("reach", "mp1", 0), ("reach", "d2a", 0), ("reach", "d2a-present", 0)])
    assert events == [("mp1", None), "world model", ("d2a", tmp_path / "wm.pt"), ("d2a-present", tmp_path / "wm.pt")]


def test_unknown_group_is_refused():
    with pytest.raises(ValueError, match="unknown group"):
        Table1Config(groups=("impossible",))
