"""The paper's Table IV on this toolkit (``d2a bench table4``): success against the number of
demonstrations (1, 2, 5, 10, 20) on Lever-Pull, Assembly, Push and Stick-Pull, every method,
both protocols, one resumable command.

The cells are ``d2a bench success``'s. One pool of ``pool`` demonstrations (the paper's largest
count, 20) is collected per task, and a cell of N demonstrations trains on its first N, so the
sets are nested (1 of 2 of 5 ...); each world model trains on the same N and validates on the
demonstrations after them (the 20-demonstration one holds out 4 of its 20). The grid runs count
by count, 5 first (where the paper claims imagination helps most), then task by task and seed
by seed. Finished cells go to ``<results>/cells`` (kept under version control), so a rerun in a
fresh checkout skips them; two processes running the same command share the grid.

The report gives the paper's layout (rows: demonstrations; columns: tasks) for both protocols,
each entry the methods' figures with the paper's MP1 / Ours beside; a per-cell CSV; a detail
table with the pooled 95 % intervals; and a plot of success against demonstrations.

Example::

    config = Table4Config(demos=(5,), tasks=("push",), algos=("mp1", "d2a"), seeds=(0,))
    cells = run(config)      # trains what is missing, then writes the report
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from benchmarks.cells import Cell, Summary, cells_csv, progress_line, read_cell, summarize
from benchmarks.paired import grid_note
from benchmarks.success import SuccessBenchConfig, cell_path, paper_table_cells, run_grid, take_shared_cells
from collectors.atomic import atomic_write_text
from d2a_agents.policy.agent import ALGORITHMS
from d2a_agents.success_plot import save_figure

TASKS = ("lever-pull", "assembly", "push", "stick-pull")
ALGOS = ("mp1", "d2a", "d2a-present")  # the grid's methods
METHOD_ORDER = (*ALGOS, *ALGORITHMS)  # the reports' columns: the grid's methods first, then the toolkit's order
DEMO_COUNTS = (5, 1, 2, 10, 20)  # the grid's order: 5 first, where the paper claims imagination helps most
# The paper's Table IV: demonstrations -> task -> (MP1, Ours) success %.
PAPER_TABLE4: dict[int, dict[str, tuple[int, int]]] = {
    1: {"lever-pull": (6, 15), "assembly": (8, 12), "push": (9, 17), "stick-pull": (1, 8)},
    2: {"lever-pull": (18, 26), "assembly": (11, 25), "push": (22, 35), "stick-pull": (7, 20)},
    5: {"lever-pull": (19, 30), "assembly": (80, 89), "push": (32, 50), "stick-pull": (52, 65)},
    10: {"lever-pull": (81, 85), "assembly": (98, 100), "push": (74, 85), "stick-pull": (74, 81)},
    20: {"lever-pull": (82, 86), "assembly": (100, 100), "push": (91, 96), "stick-pull": (82, 88)},
}


@dataclass(frozen=True)
class Table4Config:
    """What ``d2a bench table4`` runs; ``bench`` holds every per-cell setting (policy preset,
    evaluations, env options, world model); its ``tasks`` / ``algos`` / ``seeds`` / ``demos``
    are set per cell."""

    tasks: tuple[str, ...] = TASKS
    demos: tuple[int, ...] = DEMO_COUNTS
    algos: tuple[str, ...] = ALGOS
    seeds: tuple[int, ...] = (0, 1, 2)
    pool: int = max(DEMO_COUNTS)  # demonstrations collected per task, whatever counts a run asks for
    results: str = "docs/table4"  # cells/ (kept), table4.md, cells.csv, tasks.md, table4.png
    bench: SuccessBenchConfig = paper_table_cells("outputs/table4")

    def __post_init__(self) -> None:
        if not all(1 <= demos <= self.pool for demos in self.demos):
            raise ValueError(f"every demonstration count must lie in 1..pool ({self.pool}), not {self.demos}")

    def cell_config(self, demos: int) -> SuccessBenchConfig:
        """The success bench's config of the cells of ``demos`` demonstrations."""
        return dataclasses.replace(self.bench, demos=demos, pool=self.pool, algos=self.algos, seeds=self.seeds,
                                   cells=str(Path(self.results) / "cells"))


def plan(config: Table4Config) -> list[tuple[int, str, str, int]]:
    """The grid's (demos, task, algo, seed) cells in the order they run."""
    return [(demos, task, algo, seed) for demos in config.demos for task in config.tasks
            for seed in config.seeds for algo in config.algos]


def in_report_order(names: Iterable[str], order: Iterable[str]) -> tuple[str, ...]:
    """``names`` once each in ``order``'s order (any other after, as met): a report's columns
    follow the cells, not the order a run's options named them, so every run writes the same."""
    rank = {name: index for index, name in enumerate(dict.fromkeys(order))}
    return tuple(sorted(dict.fromkeys(names), key=lambda name: rank.get(name, len(rank))))


def columns(cells: list[Cell], config: Table4Config) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The report's tasks and methods: ``config``'s and any a cell holds, in the paper's task
    order and the grid's method order."""
    return (in_report_order([*config.tasks, *(cell.task for cell in cells)], TASKS),
            in_report_order([*config.algos, *(cell.algo for cell in cells)], METHOD_ORDER))


def summaries(cells: list[Cell]) -> dict[tuple[int, str, str], Summary]:
    """Per (demos, task, algo): both protocols over the seeds (honest pooled, with its interval)."""
    return {(demos, task, algo): row for demos in sorted({cell.demos for cell in cells})
            for (task, algo), row in summarize([cell for cell in cells if cell.demos == demos]).items()}


def report(cells: list[Cell], config: Table4Config) -> str:
    """Markdown in the paper's layout, once per protocol: per count and task, the methods'
    success (mean over seeds; the honest one pooled) and the paper's MP1 / Ours."""
    rows = summaries(cells)
    tasks, algos = columns(cells, config)
    bench = config.cell_config(max(config.demos))
    collected = f" (collected from env seed {bench.demo_seed} on)" if bench.demo_seed else ""
    lines = [
        f"Success (%), the paper's Table IV tasks; nested sets of the first N of {config.pool} demonstrations per "
        f"task{collected}; {bench.policy.steps} steps x batch {bench.policy.batch_size}, "
        f"{bench.policy.policy.num_points} points per cloud. Paper protocol: mean of the best 5 of "
        f"{bench.evaluations} evaluations of {bench.eval_episodes} episodes; honest: the final checkpoint on "
        f"{bench.final_episodes} new layouts per seed, pooled over seeds. Each entry: "
        f"{' / '.join(f'`{algo}`' for algo in algos)} (seeds: one count where every measured method has as many, "
        "else each method's), then the paper's MP1 / Ours; - : not measured.",
    ]
    for protocol in ("honest", "paper"):
        lines += ["", f"{protocol.capitalize()} protocol:", "", "| demos | " + " | ".join(tasks) + " |",
                  "| --- | " + " | ".join("---" for _ in tasks) + " |"]
        for demos in sorted(config.demos):
            entries = []
            for task in tasks:
                figures = [rows.get((demos, task, algo)) for algo in algos]
                measured = (" / ".join("-" if row is None else f"{100 * getattr(row, protocol):.0f}" for row in figures)
                            + f" ({_seed_counts(figures)})") if any(figures) else "-"
                paper = PAPER_TABLE4.get(demos, {}).get(task)
                entries.append(measured + (f" [paper {paper[0]} / {paper[1]}]" if paper else ""))
            lines.append(f"| {demos} | " + " | ".join(entries) + " |")
    return "\n".join([*lines, *grid_note(cells)])


def _seed_counts(figures: list[Summary | None]) -> str:
    """The seeds behind an entry's figures: one count when every measured method has as many,
    else each method's (``-`` where it has none)."""
    counts = [len(row.seeds) for row in figures if row]
    if len(set(counts)) == 1:
        return str(counts[0])
    return " / ".join("-" if row is None else str(len(row.seeds)) for row in figures)


def detail_table(cells: list[Cell]) -> str:
    """Markdown, one row per (demos, task, algo): per-seed honest figures, pooled [95 %], paper protocol."""
    lines = ["| demos | task | algo | honest per seed | honest pooled [95 %] | paper protocol |",
             "| --- | --- | --- | --- | --- | --- |"]
    for (demos, task, algo), row in summaries(cells).items():
        per_seed = " / ".join(f"{100 * rate:.0f}" for rate in row.seeds)
        lines.append(f"| {demos} | {task} | `{algo}` | {per_seed} | {100 * row.honest:.1f} "
                     f"[{100 * row.low:.1f}-{100 * row.high:.1f}] | {100 * row.paper:.1f} |")
    return "\n".join(lines)


def plot(cells: list[Cell], config: Table4Config, path: str | Path) -> Path:
    """Success against demonstrations, one panel per task: a line per method (honest, pooled
    95 % interval shaded) and the paper's MP1 and Ours as dotted lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summaries(cells)
    tasks, algos = columns(cells, dataclasses.replace(config, algos=()))  # the plot: measured methods only
    counts = sorted(config.demos)
    fig, axes = plt.subplots(1, len(tasks), figsize=(3.2 * len(tasks), 3.2), sharey=True, squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        for index, algo in enumerate(algos):
            points = [(demos, rows[demos, task, algo]) for demos in counts if (demos, task, algo) in rows]
            if not points:
                continue
            dodge = 1.06 ** (index - (len(algos) - 1) / 2)  # side by side at each count (the x axis is log)
            xs, colour = [demos * dodge for demos, _ in points], f"C{index}"  # one colour per method in every panel
            ax.plot(xs, [100 * row.honest for _, row in points], "o-", color=colour, label=algo)
            ax.fill_between(xs, [100 * row.low for _, row in points], [100 * row.high for _, row in points],
                            color=colour, alpha=0.2)
        for column, (name, style) in enumerate((("paper MP1", "k:"), ("paper Ours", "k--"))):
            xs = [demos for demos in counts if task in PAPER_TABLE4.get(demos, {})]
            ax.plot(xs, [PAPER_TABLE4[demos][task][column] for demos in xs], style, linewidth=1, label=name)
        ax.set_xscale("log")
        ax.set_xticks(counts, [str(demos) for demos in counts])
        ax.set_title(task, fontsize=9)
        ax.set_xlabel("demonstrations")
        ax.set_ylim(0, 102)
    axes[0][0].set_ylabel("success % (honest, 95 % interval)")
    legend = {label: handle for ax in axes[0] for handle, label in zip(*ax.get_legend_handles_labels(), strict=True)}
    axes[0][-1].legend(legend.values(), legend.keys(), fontsize=7, loc="lower right")  # every method, whichever panel
    return save_figure(fig, path)


def reported(config: Table4Config, max_seed: int = 10) -> Table4Config:
    """``config`` widened to what its report shows: every demonstration count, Table IV task,
    method and seed (below ``max_seed``), in the report's order, so a run of one count, task or
    method reports the others' cells and writes the same files as a run of the whole grid."""
    counts = {*config.demos, *(demos for demos in DEMO_COUNTS if demos <= config.pool)}
    return dataclasses.replace(config, demos=tuple(sorted(counts)),
                               tasks=in_report_order((*config.tasks, *TASKS), TASKS),
                               algos=in_report_order((*config.algos, *ALGORITHMS), METHOD_ORDER),
                               seeds=tuple(sorted({*config.seeds, *range(max_seed)})))


def finished_cells(config: Table4Config) -> list[Cell]:
    """The cells of ``config``'s grid already in ``results/cells``, in the grid's order."""
    return [read_cell(path) for demos, task, algo, seed in plan(config)
            if (path := cell_path(config.cell_config(demos), task, algo, seed)).exists()]


def write_report(cells: list[Cell], config: Table4Config) -> str:
    """Write table4.md, cells.csv, tasks.md and (with any cell) table4.png to ``results``."""
    results = Path(config.results)
    text = report(cells, config)
    atomic_write_text(results / "table4.md", text + "\n")
    atomic_write_text(results / "cells.csv", cells_csv(cells))
    atomic_write_text(results / "tasks.md", detail_table(cells) + "\n")
    if cells:
        plot(cells, config, results / "table4.png")
    return text


def run(config: Table4Config = Table4Config(), report_only: bool = False) -> list[Cell]:
    """Run the grid's missing cells count by count (``report_only``: only copy in those that
    ``shared_cells`` holds), then print and write the report of every finished cell (its tasks'
    and the Table IV tasks') and the CPU time the grid's cells took; returns the grid's cells."""
    for demos in config.demos:
        grid = [(task, algo, seed) for count, task, algo, seed in plan(config) if count == demos]
        (take_shared_cells if report_only else run_grid)(config.cell_config(demos), grid)
    widest = reported(config)
    cells = finished_cells(widest)
    shown = dataclasses.replace(config, demos=widest.demos)  # every count of the paper's layout
    if cells:  # the measured tasks and methods alone, so every run writes the same files
        shown = dataclasses.replace(shown, tasks=(), algos=())
    print(write_report(cells, shown))
    grid = plan(config)
    planned = set(grid)
    in_grid = [cell for cell in cells if (cell.demos, cell.task, cell.algo, cell.seed) in planned]
    print("\n" + progress_line(in_grid, [algo for _, _, algo, _ in grid]))
    return in_grid
