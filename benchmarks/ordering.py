"""Does a claimed ranking of methods hold on the cells they share?

A paper's table ranks its methods (Table I: DP < CP < DP3 < FlowPolicy < MP1 on average). This
report checks each step of such a ranking on a grid's cells: each adjacent pair of methods is
compared cell by cell as :mod:`benchmarks.paired` does (same task, demonstrations, seed, settings
and layouts), and the step is called *holds* when the higher method's mean difference over the
pairs has its whole 95 % Student-t interval above zero, *reversed* when it lies below zero, and
*not separated* otherwise. Beside it, each method's pooled success over the cells that every
method of the ranking has, so the methods are read on the same tasks and seeds.

Example::

    d2a bench order --results docs/other_methods --order dp cp dp3 flowpolicy mp1
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

from benchmarks.cells import Cell, read_cell
from benchmarks.paired import Pair, PairedSummary, cell_files, pairs_in, report_page, split_cell_name, summarize_pairs
from collectors.atomic import atomic_write_text
from collectors.evaluation import wilson_interval
from d2a_agents.success_plot import save_figure


@dataclass(frozen=True)
class OrderingConfig:
    results: tuple[str, ...]  # directories of cells (or of a grid's report, holding cells/)
    order: tuple[str, ...]  # the claimed ranking, lowest first
    tasks: tuple[str, ...] = ()  # only these tasks' cells (cell-name spelling; none: all)
    markdown: str | None = None  # where to write the report as well as printing it (none: print only)
    plot: str | None = None  # a PNG of the methods on their common cells and each step's verdict (none: no plot)

    def __post_init__(self) -> None:
        if not self.results:
            raise ValueError("give at least one directory of cells")
        if len(self.order) < 2:
            raise ValueError(f"a ranking needs at least two methods, got {list(self.order)}")
        if len(set(self.order)) != len(self.order):
            raise ValueError(f"a method appears twice in the ranking {list(self.order)}")


@dataclass(frozen=True)
class Step:
    """One step of the ranking: ``higher`` (the pairs' treated side) claimed above ``lower``."""

    lower: str
    higher: str
    pairs: list[Pair]

    @cached_property
    def summary(self) -> PairedSummary | None:
        return summarize_pairs(self.pairs) if self.pairs else None

    @property
    def verdict(self) -> str:
        summary = self.summary
        if summary is None:
            return "no shared cell"
        if summary.pairs < 2:
            return "one pair: no interval"
        if summary.low > 0:
            return "holds"
        if summary.high < 0:
            return "reversed"
        return "not separated"


def steps(config: OrderingConfig) -> list[Step]:
    """The adjacent steps of the ranking, each with its pairs over every results directory."""
    return [Step(lower, higher, pairs_in(config.results, higher, lower, tasks=config.tasks))
            for lower, higher in itertools.pairwise(config.order)]


def common_cells(config: OrderingConfig) -> dict[str, list[Cell]]:
    """Each method's cells on the names (task, seed, settings) that every method of the ranking has
    (a name in several directories: the first directory's cell)."""
    by_method: dict[str, dict[str, Path]] = {method: {} for method in config.order}
    for directory in config.results:
        for path in cell_files(directory):
            task, method, rest = split_cell_name(path.stem)
            if method in by_method and (not config.tasks or task in config.tasks):
                by_method[method].setdefault(f"{task}_{rest}", path)
    shared = set.intersection(*(set(names) for names in by_method.values()))
    return {method: [read_cell(by_method[method][name]) for name in sorted(shared)] for method in config.order}


@dataclass(frozen=True)
class Ranking:
    """What the report and the plot read, gathered once: each method's common cells and the steps."""

    order: tuple[str, ...]
    common: dict[str, list[Cell]]
    steps: list[Step]

    @property
    def shared(self) -> int:
        """How many cells every method has."""
        return len(self.common[self.order[0]])


def rank(config: OrderingConfig) -> Ranking:
    return Ranking(config.order, common_cells(config), steps(config))


def pooled_success(cells: list[Cell]) -> tuple[int, int, float, float]:
    """Final wins and episodes pooled over ``cells``, with the 95 % Wilson interval of their rate."""
    wins, episodes = sum(cell.final_wins for cell in cells), sum(cell.final_episodes for cell in cells)
    return (wins, episodes, *wilson_interval(wins, episodes))


def report(ranking: Ranking) -> str:
    """Markdown: the methods on their common cells, then each step of the ranking and its verdict."""
    claimed = " < ".join(f"`{method}`" for method in ranking.order)
    lines = [f"The ranking {claimed}, step by step on the cells each two methods share (final checkpoint; "
             "same task, demonstrations, seed, settings and layouts)", ""]
    if ranking.shared:
        tasks = sorted({cell.task for cell in ranking.common[ranking.order[0]]})
        lines += [f"On the {ranking.shared} cells every method has ({', '.join(tasks)}):", "",
                  "| method | final wins | pooled success [95 %] | paper protocol, mean over cells |",
                  "| --- | --- | --- | --- |"]
        for method, cells in ranking.common.items():
            wins, episodes, low, high = pooled_success(cells)
            paper = 100 * sum(c.paper for c in cells) / len(cells)
            lines.append(f"| `{method}` | {wins}/{episodes} | {100 * wins / episodes:.1f} "
                         f"[{100 * low:.1f}-{100 * high:.1f}] | {paper:.1f} |")
    else:
        lines.append("No cell is shared by every method of the ranking.")
    lines += ["", "| claimed | pairs | higher ahead / level / behind | mean difference (points) [95 %, t] | "
                  "pooled difference [95 %, Newcombe] | verdict |",
              "| --- | --- | --- | --- | --- | --- |"]
    for step in ranking.steps:
        summary = step.summary
        if summary is None:
            cells = ["0", "-", "-", "-"]
        else:
            interval = (f" [{100 * summary.low:+.1f}, {100 * summary.high:+.1f}]" if summary.pairs > 1 else "")
            pooled = 100 * (summary.pooled_treated - summary.pooled_control)
            cells = [str(summary.pairs), f"{summary.wins} / {summary.ties} / {summary.losses}",
                     f"{100 * summary.mean:+.1f}{interval}",
                     f"{pooled:+.1f} [{100 * summary.pooled_low:+.1f}, {100 * summary.pooled_high:+.1f}]"]
        lines.append(f"| `{step.lower}` < `{step.higher}` | " + " | ".join([*cells, step.verdict]) + " |")
    return "\n".join(lines)


def plot(ranking: Ranking, path: str | Path) -> Path:
    """Each method's pooled final-checkpoint success on the common cells with its Wilson interval,
    in the claimed order from the bottom up, and each step's verdict between its two methods."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not ranking.shared:
        raise ValueError(f"no cell is shared by every method of {list(ranking.order)}: nothing to plot")
    figure, axes = plt.subplots(figsize=(6.5, 1.0 + 0.55 * len(ranking.order)))
    for row, method in enumerate(ranking.order):
        wins, episodes, low, high = pooled_success(ranking.common[method])
        rate = 100 * wins / episodes
        axes.errorbar(rate, row, xerr=[[rate - 100 * low], [100 * high - rate]], fmt="o", color="tab:blue", capsize=3)
    for row, step in enumerate(ranking.steps):
        axes.text(1, row + 0.5, f"{step.lower} < {step.higher}: {step.verdict}", fontsize=7, va="center",
                  color="grey")
    axes.set_yticks(range(len(ranking.order)), ranking.order)
    axes.set_xlim(0, 100)
    axes.set_xlabel(f"final-checkpoint success on the {ranking.shared} cells all share (%, 95 %)")
    return save_figure(figure, path)


def run(config: OrderingConfig) -> str:
    ranking = rank(config)
    text = report(ranking)
    print(text)
    if config.plot:
        print(f"plot: {plot(ranking, config.plot)}")
    if config.markdown:
        options = [*(f"--results {directory}" for directory in config.results),
                   f"--order {' '.join(config.order)}", *(f"--task {task}" for task in config.tasks)]
        if config.plot:
            options.append(f"--plot {config.plot}")
        caption = "each method on the cells all share, each step's verdict"
        page = report_page(f"The ranking {' < '.join(config.order)}", f"d2a bench order {' '.join(options)}",
                           config.markdown, config.plot, caption, text)
        atomic_write_text(Path(config.markdown), page)
        print(f"report: {config.markdown}")
    return text
