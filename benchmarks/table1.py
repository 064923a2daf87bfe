"""The paper's Table I on this toolkit (``d2a bench table1``): the 34 Meta-World tasks by
difficulty group and the three Adroit tasks, every method, both protocols, one resumable command.

The grid is ``d2a bench success``'s cells (same data, training, evaluation and workdir layout),
ordered where the paper claims most first: group by group (Very Hard, Hard, Medium, Easy, then
Adroit), in a group seed by seed, so that a grid cut short has whole seeds of whole groups. The
Adroit cells have settings of their own (:func:`adroit_cells`): a policy imitates Adroit's
controllers only from DART demonstrations, acting on the mean of several draws
(docs/environments.md). Finished cells are written to ``<results>/cells`` (small JSON files,
meant to be kept under version control), so a rerun in a fresh checkout skips them; data,
world models and checkpoints stay in the workdir. Two processes running the same command share
the grid (each claims the next free cell).

The report (``report``) gives per group and method the mean over the group's tasks for each
seed that has every task, then mean and standard deviation over those seeds, for the paper
protocol and the honest one (with the 95 % Wilson interval of all the group's final episodes
pooled), beside the paper's rows; a per-task CSV and markdown table; and a plot.

Example::

    config = Table1Config(groups=("very_hard",), algos=("mp1",), seeds=(0,))
    cells = run(config)            # trains what is missing, then writes the report
    print(report(cells, config))
"""

from __future__ import annotations

import dataclasses
import itertools
import statistics
from dataclasses import dataclass
from pathlib import Path

import d2a_envs
from benchmarks.cells import Cell, cells_csv, progress_line, read_cell, summarize
from benchmarks.paired import grid_note, pair_cells, summary_sentence
from benchmarks.success import SuccessBenchConfig, cell_path, paper_table_cells, run_grid, take_shared_cells
from collectors.atomic import atomic_write_text
from collectors.evaluation import honest_protocol
from d2a_agents.policy.agent import ALGORITHMS
from d2a_agents.policy.train import POLICY_PRESETS
from d2a_agents.success_plot import SuccessBar, plot_success_bars

GROUPS = ("very_hard", "hard", "medium", "easy")  # Meta-World's, the grid's order: where the paper claims most first
ADROIT = "adroit"  # the group of the Adroit columns (one column per task), run after Meta-World's
TABLE1_GROUPS = (*GROUPS, ADROIT)
GROUP_TITLES = {"easy": "Easy", "medium": "Medium", "hard": "Hard", "very_hard": "Very Hard", ADROIT: "Adroit"}
ADROIT_COLUMNS = ("adroit-hammer", "adroit-door", "adroit-pen")

# The Adroit cells' own settings, those at which policies first imitated the controllers
# (docs/environments.md): demonstrations collected with the DART noise each controller
# tolerates (Pen has only its planner: plain demonstrations), 512-point clouds from 84-pixel
# depth, policies reading 256 of them, every evaluation on the mean of 8 draws per chunk.
ADROIT_DART_NOISE = {"adroit-hammer": 0.1, "adroit-door": 0.05, "adroit-pen": 0.0}
ADROIT_CLOUDS: dict[str, object] = {"num_points": 512, "image_size": 84}
ADROIT_POLICY_POINTS = 256
ADROIT_ACTION_DRAWS = 8

# The paper's Table I (success %, mean over each group's tasks; Adroit per task).
PAPER_TABLE1: dict[str, dict[str, float]] = {
    "dp": {"easy": 50.7, "medium": 11.0, "hard": 5.25, "very_hard": 22.0,
           "adroit-hammer": 16, "adroit-door": 34, "adroit-pen": 13},
    "cp": {"easy": 69.3, "medium": 21.2, "hard": 17.5, "very_hard": 30.0,
           "adroit-hammer": 45, "adroit-door": 31, "adroit-pen": 13},
    "dp3": {"easy": 87.3, "medium": 44.5, "hard": 32.7, "very_hard": 39.4,
            "adroit-hammer": 100, "adroit-door": 56, "adroit-pen": 46},
    "flowpolicy": {"easy": 84.8, "medium": 58.2, "hard": 40.2, "very_hard": 52.2,
                   "adroit-hammer": 98, "adroit-door": 61, "adroit-pen": 54},
    "mp1": {"easy": 88.2, "medium": 68.0, "hard": 58.1, "very_hard": 67.2,
            "adroit-hammer": 100, "adroit-door": 69, "adroit-pen": 58},
    "d2a": {"easy": 93.4, "medium": 74.7, "hard": 65.0, "very_hard": 74.2,
            "adroit-hammer": 100, "adroit-door": 74, "adroit-pen": 63},
}
ADROIT_NOTE = (f"Adroit columns: per task, mean ± std over seeds (honest: with the pooled 95 % Wilson interval); "
               f"10 demonstrations collected with DART noise (Hammer {ADROIT_DART_NOISE['adroit-hammer']}, Door "
               f"{ADROIT_DART_NOISE['adroit-door']}; Pen: its planner's, no noise), clouds "
               f"{ADROIT_CLOUDS['num_points']} points from {ADROIT_CLOUDS['image_size']}-pixel depth, policies reading "
               f"{ADROIT_POLICY_POINTS}, every evaluation on the mean of {ADROIT_ACTION_DRAWS} draws per chunk "
               "(docs/environments.md).")


@dataclass(frozen=True)
class Table1Config:
    """What ``d2a bench table1`` runs; ``bench`` holds every per-cell setting (policy preset,
    evaluations, env options, world model), its ``tasks`` / ``algos`` / ``seeds`` are unused."""

    groups: tuple[str, ...] = TABLE1_GROUPS
    algos: tuple[str, ...] = ("mp1", "dp3")
    seeds: tuple[int, ...] = (0, 1, 2)
    results: str = "docs/table1"  # cells/ (kept), table1.md, tasks.csv, tasks.md, table1.png
    bench: SuccessBenchConfig = paper_table_cells("outputs/table1")

    def __post_init__(self) -> None:
        unknown = set(self.groups) - set(TABLE1_GROUPS)
        if unknown:
            raise ValueError(f"unknown group(s) {sorted(unknown)}; choose from {TABLE1_GROUPS}")

    def cell_config(self) -> SuccessBenchConfig:
        """The success bench's config of every Meta-World cell, its cells kept in ``results``."""
        return dataclasses.replace(self.bench, algos=self.algos, seeds=self.seeds,
                                   cells=str(Path(self.results) / "cells"))

    def task_cell_config(self, task: str) -> SuccessBenchConfig:
        """The cells' config of ``task``: :meth:`cell_config`, with Adroit's own settings on Adroit."""
        return adroit_cells(self.cell_config(), task) if task in ADROIT_COLUMNS else self.cell_config()


def adroit_cells(bench: SuccessBenchConfig, task: str) -> SuccessBenchConfig:
    """``bench`` with the Adroit settings for ``task``: its DART noise, the Adroit clouds, the
    policy's points and the evaluations' draws (the policy preset's budget otherwise kept)."""
    policy = dataclasses.replace(bench.policy.policy, num_points=ADROIT_POLICY_POINTS)
    return dataclasses.replace(bench, dart_noise=ADROIT_DART_NOISE[task], env_kwargs=ADROIT_CLOUDS,
                               policy=dataclasses.replace(bench.policy, policy=policy),
                               action_draws=ADROIT_ACTION_DRAWS)


def group_tasks(group: str) -> list[str]:
    """The Table I tasks of a difficulty group (or the Adroit columns), in the task table's order."""
    if group == ADROIT:
        return list(ADROIT_COLUMNS)
    return [spec.name for spec in d2a_envs.list_tasks(suite="metaworld", difficulty=group, table1=True)]


def plan(config: Table1Config) -> list[tuple[str, str, int]]:
    """The grid's (task, algo, seed) cells in the order they run: group by group, in a group
    seed by seed, then task by task and method by method."""
    return [(task, algo, seed) for group in config.groups for seed in config.seeds
            for task in group_tasks(group) for algo in config.algos]


@dataclass(frozen=True)
class GroupRow:
    """One method on one group: means over the group's tasks per complete seed, their mean and
    standard deviation, and the honest protocol's interval over the final episodes of those seeds
    pooled (of every finished cell while no seed is complete, as the partial means)."""

    paper_by_seed: tuple[float, ...]
    honest_by_seed: tuple[float, ...]
    low: float
    high: float
    tasks_done: int  # tasks with at least one finished seed
    tasks: int
    partial_paper: float  # means over every finished cell, complete seeds or not
    partial_honest: float

    @property
    def seeds(self) -> int:
        return len(self.honest_by_seed)


def group_rows(cells: list[Cell]) -> dict[tuple[str, str], GroupRow]:
    """Per (group, algo) with at least one cell: a seed counts where every task of the group has it."""
    group_of = {task: group for group in GROUPS for task in group_tasks(group)}
    rows = {}
    for group in GROUPS:
        tasks = group_tasks(group)
        for algo in dict.fromkeys(cell.algo for cell in cells):
            mine = [cell for cell in cells if cell.algo == algo and group_of.get(cell.task) == group]
            if not mine:
                continue
            by_seed: dict[int, dict[str, Cell]] = {}
            for cell in mine:
                by_seed.setdefault(cell.seed, {})[cell.task] = cell
            complete = [per_task for _, per_task in sorted(by_seed.items()) if len(per_task) == len(tasks)]
            pooled = [cell for per_task in complete for cell in per_task.values()] or mine  # as the mean's seeds
            wins, episodes = sum(c.final_wins for c in pooled), sum(c.final_episodes for c in pooled)
            _, low, high = honest_protocol([True] * wins + [False] * (episodes - wins))
            rows[group, algo] = GroupRow(
                tuple(statistics.fmean(c.paper for c in per_task.values()) for per_task in complete),
                tuple(statistics.fmean(c.honest for c in per_task.values()) for per_task in complete),
                low, high, len({cell.task for cell in mine}), len(tasks),
                statistics.fmean(c.paper for c in mine), statistics.fmean(c.honest for c in mine))
    return rows


def _mean_std(values: tuple[float, ...]) -> str:
    spread = statistics.stdev(values) if len(values) > 1 else 0.0
    return f"{100 * statistics.fmean(values):.1f} ± {100 * spread:.1f}"


def _group_entry(row: GroupRow | None, protocol: str) -> str:
    if row is None:
        return "-"
    if not row.seeds:
        partial = row.partial_paper if protocol == "paper" else row.partial_honest
        return f"{100 * partial:.1f} over {row.tasks_done}/{row.tasks} tasks"
    values = row.paper_by_seed if protocol == "paper" else row.honest_by_seed
    interval = f" [{100 * row.low:.0f}-{100 * row.high:.0f}]" if protocol == "honest" else ""
    return f"{_mean_std(values)}{interval} ({row.seeds} seed{'s' if row.seeds > 1 else ''})"


def report(cells: list[Cell], config: Table1Config) -> str:
    """Markdown: the paper-format table (per group: mean ± std over complete seeds, both
    protocols; the honest one with its pooled 95 % interval) beside the paper's rows."""
    rows = group_rows(cells)
    # The default methods' rows first, then the others as the cells come: the same rows whatever
    # subset of the grid this run covers.
    algos = list(dict.fromkeys([*Table1Config.algos, *(cell.algo for cell in cells)]))
    header = ([GROUP_TITLES[group] for group in GROUPS[::-1]]
              + [_adroit_title(task) for task in ADROIT_COLUMNS])
    bench = config.cell_config()
    lines = [
        f"Success (%), Meta-World groups of the paper's Table I; {bench.demos} demonstrations per task, the "
        f"`{_preset_name(bench)}` policy preset ({bench.policy.steps} steps x batch {bench.policy.batch_size}, "
        f"{bench.policy.policy.num_points} points per cloud), clouds {_env_text(bench.env_kwargs)}. Paper protocol: "
        f"mean of the best 5 of {bench.evaluations} evaluations of {bench.eval_episodes} episodes during "
        f"training; honest: the final checkpoint on {bench.final_episodes} new layouts per seed. Each entry: "
        "mean ± std over seeds of the group's mean over its tasks (a seed counts once every task of the group "
        "has it), the honest one with the 95 % Wilson interval of the group's final episodes pooled; "
        "'x over k/N tasks': a group not yet complete for any seed, the mean over its finished cells.",
        "",
        "| method | protocol | " + " | ".join(header) + " |",
        "| --- | --- | " + " | ".join("---" for _ in header) + " |",
    ]
    for algo in algos:
        for protocol in ("paper", "honest"):
            entries = [_group_entry(rows.get((group, algo)), protocol) for group in GROUPS[::-1]]
            entries += [_adroit_entry([cell for cell in cells if (cell.task, cell.algo) == (task, algo)], protocol)
                        for task in ADROIT_COLUMNS]
            lines.append(f"| `{algo}` | {protocol} | " + " | ".join(entries) + " |")
    for method, values in PAPER_TABLE1.items():
        entries = [f"{values[key]:g}" for key in (*GROUPS[::-1], *ADROIT_COLUMNS)]
        lines.append(f"| {method} (paper) | paper | " + " | ".join(entries) + " |")
    lines += ["", ADROIT_NOTE, *grid_note(cells), *paired_by_group(cells)]
    return "\n".join(lines)


def paired_by_group(cells: list[Cell]) -> list[str]:
    """Per group, `d2a` against its control and against `mp1` cell by cell: where the paper
    claims imagination helps (most on Very Hard), the grid's answer group by group."""
    lines = []
    for group in TABLE1_GROUPS:
        tasks = set(group_tasks(group))
        in_group = [cell for cell in cells if cell.task in tasks]
        lines += [f"- {GROUP_TITLES[group]}: {summary_sentence(pairs, 'd2a', reference)}"
                  for reference in ("d2a-present", "mp1") if (pairs := pair_cells(in_group, "d2a", reference))]
    return ["", "Per group (`d2a bench paired --task ...` with the group's tasks):", "", *lines] if lines else []


def _adroit_title(task: str) -> str:
    """An Adroit column's title: ``adroit-door`` -> ``Adroit Door``."""
    return "Adroit " + task.split("-")[1].title()


def _adroit_entry(runs: list[Cell], protocol: str) -> str:
    """One Adroit task's entry: mean ± std over its seeds, the honest one with the pooled interval."""
    if not runs:
        return "-"
    values = tuple(cell.paper if protocol == "paper" else cell.honest for cell in runs)
    interval = ""
    if protocol == "honest":
        (pooled,) = summarize(runs).values()
        interval = f" [{100 * pooled.low:.0f}-{100 * pooled.high:.0f}]"
    return f"{_mean_std(values)}{interval} ({len(runs)} seed{'s' if len(runs) > 1 else ''})"


def _preset_name(bench: SuccessBenchConfig) -> str:
    return next((name for name, preset in POLICY_PRESETS.items() if preset == bench.policy), "custom")


def _env_text(env_kwargs: dict[str, object]) -> str:
    return ", ".join(f"{key} {value}" for key, value in env_kwargs.items()) or "the env's defaults"


def task_csv(cells: list[Cell]) -> str:
    """One row per cell, with its task's difficulty group (``adroit`` for the Adroit columns)."""
    group_of = {task: group for group in TABLE1_GROUPS for task in group_tasks(group)}
    return cells_csv(cells, {"group": lambda cell: group_of.get(cell.task, "-")})


def task_table(cells: list[Cell]) -> str:
    """Markdown, one row per task: per method, paper / honest over its seeds [pooled 95 %] (seeds)."""
    summaries = summarize(cells)
    algos = list(dict.fromkeys(algo for _, algo in summaries))
    lines = ["| group | task | " + " | ".join(f"`{algo}`" for algo in algos) + " |",
             "| --- | --- | " + " | ".join("---" for _ in algos) + " |"]
    for group in TABLE1_GROUPS:
        for task in group_tasks(group):
            entries = []
            for algo in algos:
                row = summaries.get((task, algo))
                seeds = sum(1 for cell in cells if (cell.task, cell.algo) == (task, algo))
                entries.append("-" if row is None else (
                    f"{100 * row.paper:.0f} / {100 * row.honest:.0f} [{100 * row.low:.0f}-{100 * row.high:.0f}]"
                    f" ({seeds})"))
            if any(entry != "-" for entry in entries):
                lines.append(f"| {GROUP_TITLES[group]} | {task} | " + " | ".join(entries) + " |")
    return "\n".join(lines)


def plot(cells: list[Cell], path: str | Path) -> Path:
    """Bars per group (and Adroit task) and method: honest mean over complete seeds (pooled 95 %
    interval, seeds as dots), the paper's Table I value for that method as a triangle."""
    bars: dict[str, dict[str, SuccessBar]] = {}
    for (group, algo), row in group_rows(cells).items():
        if row.seeds:
            bars.setdefault(algo, {})[GROUP_TITLES[group]] = SuccessBar(
                statistics.fmean(row.honest_by_seed), row.low, row.high, row.honest_by_seed,
                marker=PAPER_TABLE1[algo][group] / 100 if algo in PAPER_TABLE1 else None)
    for (task, algo), summary in summarize([cell for cell in cells if cell.task in ADROIT_COLUMNS]).items():
        bars.setdefault(algo, {})[_adroit_title(task)] = SuccessBar(
            statistics.fmean(summary.seeds), summary.low, summary.high, summary.seeds,
            marker=PAPER_TABLE1[algo][task] / 100 if algo in PAPER_TABLE1 else None)
    return plot_success_bars(bars, path, "Table I, honest protocol: group means over tasks, Adroit per task (bars, "
                                         "pooled 95 % interval; dots: seeds); triangles: the paper's value")


def write_report(cells: list[Cell], config: Table1Config) -> str:
    """Write table1.md, tasks.csv, tasks.md and table1.png to ``results``; returns table1.md's text."""
    results = Path(config.results)
    text = report(cells, config)
    atomic_write_text(results / "table1.md", text + "\n")
    atomic_write_text(results / "tasks.csv", task_csv(cells))
    atomic_write_text(results / "tasks.md", task_table(cells) + "\n")
    if any(row.seeds for row in group_rows(cells).values()) or any(cell.task in ADROIT_COLUMNS for cell in cells):
        plot(cells, results / "table1.png")
    return text


def finished_cells(config: Table1Config, max_seed: int = 10) -> list[Cell]:
    """Every Table I cell already in ``results/cells`` at this config's per-cell settings, of any
    group, method and seed below ``max_seed``, in the full grid's order whatever this run's
    methods and seeds: a run of one group or method reports the others' finished cells too, and
    writes the same report files as a run of the whole grid."""
    everything = dataclasses.replace(config, groups=TABLE1_GROUPS,
                                     algos=tuple(dict.fromkeys((*Table1Config.algos, *ALGORITHMS))),
                                     seeds=tuple(sorted({*config.seeds, *range(max_seed)})))
    settings = {task: config.task_cell_config(task) for group in TABLE1_GROUPS for task in group_tasks(group)}
    return [read_cell(path) for key in plan(everything) if (path := cell_path(settings[key[0]], *key)).exists()]


def run(config: Table1Config = Table1Config(), report_only: bool = False) -> list[Cell]:
    """Run the grid's missing cells (``report_only``: only copy in those that ``shared_cells``
    holds), then print and write the report of every finished cell, and the one-thread hours the
    grid's cells took and the rest would take at their rate; returns the grid's cells."""
    grid = plan(config)
    for settings, cells in itertools.groupby(grid, key=lambda key: config.task_cell_config(key[0])):
        # Meta-World's cells share one config; each Adroit task has its own
        (take_shared_cells if report_only else run_grid)(settings, list(cells))
    cells = finished_cells(config)
    print(write_report(cells, config))
    planned = set(grid)
    in_grid = [cell for cell in cells if (cell.task, cell.algo, cell.seed) in planned]
    print("\n" + progress_line(in_grid, [algo for _, algo, _ in grid]))
    return in_grid
