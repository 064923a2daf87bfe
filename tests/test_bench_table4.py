"""The Table IV bench: its order, its paper-layout figures against hand computations, its files."""

from __future__ import annotations

import dataclasses

import pytest

import benchmarks.success as success
from benchmarks.cells import Cell, read_cell
from benchmarks.success import cell_path
from benchmarks.table4 import Table4Config, plan, report, run
from d2a.cli import main


def _cell(task: str, algo: str, seed: int, demos: int, wins: int, periodic: list[float] | None = None) -> Cell:
    return Cell(task, algo, seed, periodic or [wins / 100], wins, 100, train_seconds=600.0, final_seconds=300.0,
                demos=demos)


def _row(text: str, protocol: str, demos: int) -> list[str]:
    section = text.split(f"\n{protocol.capitalize()} protocol:\n")[1]
    line = next(line for line in section.splitlines() if line.startswith(f"| {demos} |"))
    return [entry.strip() for entry in line.split("|")[2:-1]]


def test_plan_runs_count_by_count_five_first():
    config = Table4Config(algos=("mp1", "d2a"), seeds=(0, 1))
    cells = plan(config)
    assert len(cells) == 5 * 4 * 2 * 2
    assert [demos for demos, *_ in cells[::16]] == [5, 1, 2, 10, 20]
    assert cells[:4] == [(5, "lever-pull", "mp1", 0), (5, "lever-pull", "d2a", 0), (5, "lever-pull", "mp1", 1),
                         (5, "lever-pull", "d2a", 1)]


def test_report_in_the_papers_layout_keeps_counts_apart():
    cells = [_cell("push", "mp1", 0, 5, 30, periodic=[0.1, 0.6]), _cell("push", "mp1", 1, 5, 40, periodic=[0.2]),
             _cell("push", "d2a", 0, 5, 50), _cell("push", "mp1", 0, 10, 90)]
    text = report(cells, Table4Config(algos=("mp1", "d2a", "d2a-present")))
    lever, assembly, push, stick = _row(text, "honest", 5)
    # Honest: mp1 pools 70 wins of 200 episodes over 2 seeds; d2a one seed; d2a-present none.
    assert push == "35 / 50 / - (2 / 1 / -) [paper 32 / 50]"
    assert lever == "- [paper 19 / 30]"
    # Paper protocol: mp1 seeds average (0.35 + 0.2) / 2 = 27.5 (rounded to 28).
    assert _row(text, "paper", 5)[2] == "28 / 50 / - (2 / 1 / -) [paper 32 / 50]"
    assert _row(text, "honest", 10)[2] == "90 / - / - (1) [paper 74 / 85]"
    assert _row(text, "honest", 1)[2] == "- [paper 9 / 17]"
    assert "of 20 demonstrations per task;" in text  # the default pool, from env seed 0


def test_report_names_another_set_of_demonstrations():
    config = Table4Config(algos=("d2a",))
    config = dataclasses.replace(config, bench=dataclasses.replace(config.bench, demo_seed=1000))
    text = report([_cell("push", "d2a", 0, 2, 24)], config)
    assert "of 20 demonstrations per task (collected from env seed 1000 on);" in text


def test_report_only_writes_the_files_from_stored_cells(tmp_path, capsys):
    config = Table4Config(tasks=("push",), demos=(5,), algos=("mp1",), seeds=(0, 1), results=str(tmp_path))
    success._store(config.cell_config(5), _cell("push", "mp1", 0, 5, 30))
    assert success.cell_path(config.cell_config(5), "push", "mp1", 0).stem.endswith("_d5")
    run(config, report_only=True)
    assert "1 of 2 cells finished, 0.2 one-thread hours" in capsys.readouterr().out
    assert (tmp_path / "table4.png").stat().st_size > 0
    assert "| 5 | push | `mp1` | 30 |" in (tmp_path / "tasks.md").read_text()
    assert len((tmp_path / "cells.csv").read_text().splitlines()) == 2


def test_a_run_of_one_count_and_method_reports_every_finished_cell(tmp_path, capsys):
    """A `--demos 10 --algo cp` run keeps the 5-demonstration `mp1` cells another run stored in
    its report (after its own method), and its progress line counts its own grid only."""
    config = Table4Config(tasks=("push",), demos=(10,), algos=("cp",), seeds=(0,), results=str(tmp_path))
    wider = Table4Config(tasks=("push",), results=str(tmp_path))
    success._store(wider.cell_config(5), _cell("push", "mp1", 0, 5, 30))
    success._store(wider.cell_config(10), _cell("push", "cp", 0, 10, 80))
    cells = run(config, report_only=True)
    assert [(cell.algo, cell.demos) for cell in cells] == [("cp", 10)]
    assert "1 of 1 cells finished" in capsys.readouterr().out
    text = (tmp_path / "table4.md").read_text()
    assert _row(text, "honest", 5)[0] == "30 / - (1) [paper 32 / 50]"  # columns: `mp1`, then `cp`
    assert _row(text, "honest", 10)[0] == "- / 80 (1) [paper 74 / 85]"


def test_every_run_writes_the_same_report_whatever_its_options_order(tmp_path, capsys):
    """Two runs over the same stored cells, one naming a task and its methods in another order,
    write byte-identical reports: the measured tasks and methods, in the paper's and the grid's order."""
    wider = Table4Config(results=str(tmp_path))
    stored = (("push", "d2a", 3, 31), ("push", "mp1", 0, 13), ("lever-pull", "d2a-present", 0, 40))
    for task, algo, seed, wins in stored:
        success._store(wider.cell_config(2), _cell(task, algo, seed, 2, wins))
    written = []
    for config in (wider, Table4Config(demos=(2,), results=str(tmp_path)),
                   Table4Config(demos=(2,), tasks=("push",), algos=("d2a-present", "d2a", "mp1"), seeds=(4, 3),
                                results=str(tmp_path))):
        run(config, report_only=True)
        written.append({name: (tmp_path / name).read_text() for name in ("table4.md", "cells.csv", "tasks.md")})
    assert written[0] == written[1] == written[2]
    assert _row(written[1]["table4.md"], "honest", 20) == ["- [paper 82 / 86]", "- [paper 91 / 96]"]  # every count
    assert "Each entry: `mp1` / `d2a` / `d2a-present`" in written[1]["table4.md"]
    assert _row(written[1]["table4.md"], "honest", 2) == ["- / - / 40 (1) [paper 18 / 26]",
                                                         "13 / 31 / - (1) [paper 22 / 35]"]  # measured tasks only


def test_counts_beyond_the_pool_are_refused():
    with pytest.raises(ValueError, match="1..pool"):
        Table4Config(demos=(5, 25))


def test_cli_options(monkeypatch):
    import benchmarks.table4

    seen = {}
    monkeypatch.setattr(benchmarks.table4, "run", lambda config, report_only: seen.update(config=config,
                                                                                           report=report_only))
    main(["bench", "table4"])
    assert seen == {"config": Table4Config(), "report": False}
    main(["bench", "table4", "--task", "push", "--demos", "5", "--demos", "1", "--algo", "d2a-change", "--seed", "1",
          "--evaluations", "1", "--report"])
    config = seen["config"]
    assert (config.tasks, config.demos, config.algos, config.seeds) == (("push",), (5, 1), ("d2a-change",), (1,))
    assert config.bench.evaluations == 1 and seen["report"]
    assert (config.cell_config(1).demos, config.cell_config(1).pool) == (1, 20)
    main(["bench", "table4", "--demos", "2", "--wm-rollouts", "20", "--rollout-noise", "0.2"])
    cell_config = seen["config"].cell_config(2)
    assert (cell_config.wm_rollouts, cell_config.rollout_noise, cell_config.wm_policy_rollouts) == (20, 0.2, None)
    main(["bench", "table4", "--demos", "2", "--wm-rollouts", "20", "--wm-policy-rollouts", "d2a",
          "--wm-policy-seed", "1"])
    cell_config = seen["config"].cell_config(2)
    assert (cell_config.wm_policy_rollouts, cell_config.wm_policy_seed) == ("d2a", 1)
    main(["bench", "table4", "--demos", "2", "--wm-without-actions"])
    cell_config = seen["config"].cell_config(2)
    assert not cell_config.world_model.reads_actions
    assert dataclasses.replace(cell_config.world_model, reads_actions=True) == Table4Config().bench.world_model
    # The imagining cells (and the world model) are named apart; the others are shared.
    assert "_wmnoact" in cell_path(cell_config, "push", "d2a", 0).name
    assert cell_path(cell_config, "push", "mp1", 0) == cell_path(Table4Config().cell_config(2), "push", "mp1", 0)


def test_the_plot_keeps_one_colour_per_method_and_names_every_method(tmp_path, monkeypatch):
    """A method missing from one panel shifts neither the others' colours nor leaves the legend."""
    import benchmarks.table4 as table4

    figures = []
    monkeypatch.setattr(table4, "save_figure", lambda figure, path: figures.append(figure) or path)
    cells = [_cell("lever-pull", "mp1", 0, 5, 30), _cell("lever-pull", "d2a", 0, 5, 50), _cell("push", "d2a", 0, 5, 70)]
    table4.plot(cells, Table4Config(tasks=("push", "lever-pull"), demos=(5,)), tmp_path / "t4.png")
    lever, push = figures[0].axes  # the paper's task order, whatever the config's
    colour = {ax: {line.get_label(): line.get_color() for line in ax.get_lines()} for ax in (push, lever)}
    assert colour[push]["d2a"] == colour[lever]["d2a"] != colour[lever]["mp1"]
    assert "mp1" not in colour[push]
    # The legend (last panel) names every method, the one missing there too.
    assert [text.get_text() for text in push.get_legend().get_texts()] == ["mp1", "d2a", "paper MP1", "paper Ours"]
    # Methods stand side by side around the count, in their order.
    assert lever.get_lines()[0].get_xdata()[0] < 5 < lever.get_lines()[1].get_xdata()[0]


def test_another_grids_cells_on_the_same_demonstrations_are_copied_not_rerun(tmp_path, capsys):
    """Table I's 10 demonstrations are the first 10 of Table IV's 20: `--shared-cells` takes its
    cells of methods without a world model (nothing is collected or trained here), never an
    imagining one, whose world model's training split depends on the collection's size."""
    import dataclasses
    import json

    config = Table4Config(tasks=("push",), demos=(10,), algos=("mp1", "d2a-present"), seeds=(0,),
                          results=str(tmp_path / "t4"))
    bench = dataclasses.replace(config.cell_config(10), shared_cells=(str(tmp_path / "t1"),))
    (tmp_path / "t1").mkdir()
    for algo, wins in (("mp1", 77), ("d2a-present", 71), ("d2a", 80)):
        (tmp_path / "t1" / success.cell_path(bench, "push", algo, 0).name).write_text(
            json.dumps(dataclasses.asdict(_cell("push", algo, 0, 10, wins))))
    main(["bench", "table4", "--demos", "10", "--task", "push", "--algo", "mp1", "--algo", "d2a-present",
          "--seed", "0", "--results", str(tmp_path / "t4"), "--workdir", str(tmp_path / "work"),
          "--shared-cells", str(tmp_path / "t1")])
    assert capsys.readouterr().out.count("taken from") == 2
    assert read_cell(success.cell_path(bench, "push", "d2a-present", 0)).final_wins == 71  # now its own
    assert not (tmp_path / "work" / "data").exists()
    assert success._take_shared(bench, "push", "d2a", 0) is None
    assert not success.cell_path(bench, "push", "d2a", 0).exists()
    # A report takes what the other grid finished since (`make reports`), and trains nothing.
    (tmp_path / "t1" / success.cell_path(bench, "push", "mp1", 1).name).write_text(
        json.dumps(dataclasses.asdict(_cell("push", "mp1", 1, 10, 64))))
    main(["bench", "table4", "--demos", "10", "--task", "push", "--algo", "mp1", "--seed", "0", "--seed", "1",
          "--results", str(tmp_path / "t4"), "--workdir", str(tmp_path / "work"),
          "--shared-cells", str(tmp_path / "t1"), "--report"])
    assert capsys.readouterr().out.count("taken from") == 1
    assert read_cell(success.cell_path(bench, "push", "mp1", 1)).final_wins == 64
    assert not (tmp_path / "work").exists()
