"""Two methods compared on the cells they share: does ``algo`` beat ``control`` on the same
task, demonstrations, training seed, settings and evaluation layouts?

A grid's cells are files named ``<task>_<algo>_s<seed>_<settings>.json``; two cells pair when
their names differ only in the method. Each pair gives a difference in final-checkpoint
success. Over the pairs: wins / ties / losses, the mean difference with a Student-t interval
(the pairs are the units, so seed-to-seed spread counts), and the pooled episodes' difference
with Newcombe's hybrid score interval (it treats the two methods' episodes as independent;
they share their layouts, so it is conservative).

Example::

    d2a bench paired --results docs/table1/points128 --results docs/table4/points128 \\
        --algo d2a --control d2a-present --reference mp1 --plot outputs/paired.png

With a ``reference`` method (the baseline both should beat, ``mp1`` by default), each pair also
shows the reference's cell of the same name where there is one, and the pairs that have one are
summarised against it too: is ``algo`` above both its control and the baseline? Each side also
shows how much its policy reads its second cloud (its last perception check, as its cell keeps it,
or for cells stored before they kept it, its checkpoint in one of ``runs``, the grids' work
directories), and whether that goes with the difference.

Where the pairs span several settings (a pair's name less its seed: task, demonstrations and the
grid's settings), each setting with two pairs or more is also tested on its own (Student's paired
t test, two-sided) and the p-values are adjusted for being read together (Holm): a lead found by
looking at many settings is then weighed against the number looked at.
"""

from __future__ import annotations

import math
import os
import re
import statistics
from dataclasses import dataclass
from pathlib import Path

from scipy.stats import spearmanr
from scipy.stats import t as student_t

from benchmarks.cells import Cell, read_cell
from collectors.atomic import atomic_write_text
from collectors.evaluation import wilson_interval
from d2a_agents.checkpoint import load_checkpoint
from d2a_agents.policy.checkpoints import CHECKPOINT_NAME
from d2a_agents.policy.perception import Reliance
from d2a_agents.success_plot import save_figure


@dataclass(frozen=True)
class PairedConfig:
    results: tuple[str, ...]  # directories of cells (or of a grid's report, holding cells/)
    algo: str = "d2a"
    control: str = "d2a-present"
    reference: str | None = "mp1"  # a third method beside each pair, compared over them (none, or a side: no column)
    plot: str | None = None  # where to draw the per-pair differences (none: no plot)
    markdown: str | None = None  # where to write the report as well as printing it (none: print only)
    tasks: tuple[str, ...] = ()  # only these tasks' pairs (cell-name spelling, e.g. adroit-door; none: all)
    demos: tuple[int, ...] = ()  # only the pairs trained on these numbers of demonstrations (none: all)
    runs: tuple[str, ...] = ()  # work directories whose runs/<cell name>/ hold the cells' checkpoints (none: not read)

    def __post_init__(self) -> None:
        if not self.results:
            raise ValueError("give at least one directory of cells")
        if self.algo == self.control:
            raise ValueError(f"--algo and --control are both {self.algo!r}: nothing to compare")
        if self.reference in (self.algo, self.control):
            object.__setattr__(self, "reference", None)  # already a side of the pair: no third column


@dataclass(frozen=True)
class Pair:
    """Two cells of one task, seed and settings, one per method; ``name``: the cell name less the
    method; ``reference``: a third method's cell of the same name, if asked for and there."""

    name: str
    treated: Cell
    control: Cell
    reference: Cell | None = None

    @property
    def difference(self) -> float:
        return self.treated.honest - self.control.honest


@dataclass(frozen=True)
class PairedSummary:
    """Differences are ``algo`` minus ``control`` in final-checkpoint success (fractions)."""

    pairs: int
    wins: int
    ties: int
    losses: int
    mean: float
    low: float  # Student-t 95 % interval of the mean over pairs (nan with one pair)
    high: float
    pooled_treated: float
    pooled_control: float
    pooled_low: float  # Newcombe's hybrid score 95 % interval of the pooled difference
    pooled_high: float
    treated_interval: tuple[float, float]  # each pooled rate's Wilson 95 % interval
    control_interval: tuple[float, float]

    @property
    def intervals_apart(self) -> bool:
        """Whether the two pooled rates' Wilson intervals share no point."""
        (treated_low, treated_high), (control_low, control_high) = self.treated_interval, self.control_interval
        return treated_low > control_high or control_low > treated_high


def cell_files(directory: str | Path) -> list[Path]:
    """The cell files of a directory of cells or of a grid report's directory (``<dir>/cells``)."""
    directory = Path(directory)
    cells = directory / "cells" if (directory / "cells").is_dir() else directory
    if not cells.is_dir():
        raise ValueError(f"no directory of cells at {directory}")
    return sorted(cells.glob("*.json"))


def find_pairs(files: list[Path], algo: str, control: str, reference: str | None = None) -> list[Pair]:
    """Every ``algo`` cell whose ``control`` twin (same name, the other method) is among ``files``
    (the cells of one directory: names are unique there), with its ``reference`` twin if any."""
    by_name = {path.stem: path for path in files}
    pairs = []
    for stem, path in by_name.items():
        task, method, rest = split_cell_name(stem)
        twin = by_name.get(f"{task}_{control}_{rest}")
        if method == algo and twin is not None:
            third = by_name.get(f"{task}_{reference}_{rest}") if reference else None
            pairs.append(Pair(f"{task}_{rest}", read_cell(path), read_cell(twin),
                              read_cell(third) if third is not None else None))
    return pairs


def pairs_in(directories: tuple[str, ...], algo: str, control: str, reference: str | None = None,
             tasks: tuple[str, ...] = (), demos: tuple[int, ...] = ()) -> list[Pair]:
    """The pairs of every directory (of ``tasks`` and ``demos`` demonstrations only, when given), in
    order; a pair found again in a later directory with the same two cells (cells one grid copied from
    another, ``--shared-cells``) counts once, while a pair of the same name with another cell on either
    side is a pair of its own."""
    seen, pairs = set(), []
    for directory in directories:
        for pair in find_pairs(cell_files(directory), algo, control, reference):
            key = (pair.name, repr(pair.treated), repr(pair.control))
            wanted = (not tasks or pair.treated.task in tasks) and (not demos or pair.treated.demos in demos)
            if wanted and key not in seen:
                seen.add(key)
                pairs.append(pair)
    return pairs


def second_cloud_reliance(cell: Cell, pair_name: str, runs: tuple[str, ...]) -> float | None:
    """How much ``cell``'s policy reads its second cloud (the imagined one, or the control's second copy
    of the present): its last perception check's error with that cloud alone shuffled over the intact
    error, as the cell keeps it, else from ``<dir>/runs/<cell name>/`` of the first of ``runs`` holding
    its checkpoint; None where neither has it or the policy has no second cloud."""
    check = cell.reliance
    if check is None:
        name = f"{cell.task}_{cell.algo}_{pair_name[len(cell.task) + 1:]}"
        path = next((found for directory in runs
                     if (found := Path(directory) / "runs" / name / CHECKPOINT_NAME).is_file()), None)
        checks = load_checkpoint(path, "policy").get("reliance") if path is not None else None
        check = checks[-1] if checks else None
    return Reliance.from_record(check).imagined_ratio if check is not None else None


def reliance_sentence(pairs: list[Pair], ratios: list[tuple[float | None, float | None]], algo: str,
                      control: str) -> str:
    """The two sides' reliance on their second cloud over the pairs that have both, and whether
    ``algo``'s reliance goes with its difference from ``control`` (Spearman's rank correlation)."""
    known = [(pair.difference, mine, theirs) for pair, (mine, theirs) in zip(pairs, ratios, strict=True)
             if mine is not None and theirs is not None]
    if len(known) < 3:
        return f"Reliance on the second cloud: {len(known)} pair(s) with both checkpoints, too few to read."
    differences, mine, theirs = zip(*known, strict=True)
    rho, p_value = spearmanr(mine, differences)
    return (f"Reliance on the second cloud (final perception check, that cloud alone shuffled over intact), over the "
            f"{len(known)} pairs with both checkpoints: `{algo}` median x{statistics.median(mine):.1f}, `{control}` "
            f"median x{statistics.median(theirs):.1f}; Spearman's rho between `{algo}`'s reliance and its difference "
            f"from `{control}`: {rho:+.2f} (p = {p_value:.2f}).")


def against_reference(pairs: list[Pair]) -> list[Pair]:
    """The pairs that have a reference cell, re-paired as ``algo`` against the reference."""
    return [Pair(pair.name, pair.treated, pair.reference) for pair in pairs if pair.reference is not None]


def pair_cells(cells: list[Cell], algo: str, control: str) -> list[Pair]:
    """The pairs among one grid's cells (one setting per task), matched on task,
    demonstrations and seed, in the ``algo`` cells' order."""
    controls = {(cell.task, cell.demos, cell.seed): cell for cell in cells if cell.algo == control}
    return [Pair(f"{cell.task}_d{cell.demos}_s{cell.seed}", cell, controls[cell.task, cell.demos, cell.seed])
            for cell in cells if cell.algo == algo and (cell.task, cell.demos, cell.seed) in controls]


def grid_note(cells: list[Cell], algo: str = "d2a", control: str = "d2a-present") -> list[str]:
    """Lines closing a grid's report: ``algo`` against ``control`` over the grid's pairs (none
    without a pair)."""
    pairs = pair_cells(cells, algo, control)
    if not pairs:
        return []
    return ["", f"`{algo}` against its control `{control}` cell by cell (same task, demonstrations, seed and "
                f"layouts; `d2a bench paired`): {summary_sentence(pairs, algo, control)}"]


def split_cell_name(stem: str) -> tuple[str, str, str]:
    """(task, method, the rest) of a cell name ``<task>_<method>_<rest>``."""
    parts = stem.split("_", 2)
    return (parts[0], parts[1], parts[2]) if len(parts) == 3 else (stem, "", "")


def newcombe_interval(wins_a: int, trials_a: int, wins_b: int, trials_b: int) -> tuple[float, float]:
    """95 % interval of the difference of two independent proportions, a - b: Newcombe's
    hybrid score method (his method 10), built from each proportion's Wilson interval."""
    rate_a, rate_b = wins_a / trials_a, wins_b / trials_b
    (low_a, high_a), (low_b, high_b) = wilson_interval(wins_a, trials_a), wilson_interval(wins_b, trials_b)
    difference = rate_a - rate_b
    return (difference - math.hypot(rate_a - low_a, high_b - rate_b),
            difference + math.hypot(high_a - rate_a, rate_b - low_b))


def summarize_pairs(pairs: list[Pair]) -> PairedSummary:
    """Wins / ties / losses, the mean difference over pairs with its Student-t interval, and the
    pooled episodes' rates with their Wilson intervals and Newcombe's interval of their difference."""
    if not pairs:
        raise ValueError("no pairs to summarise")
    differences = [pair.difference for pair in pairs]
    mean = statistics.fmean(differences)
    if len(pairs) > 1:
        half = student_t.ppf(0.975, len(pairs) - 1) * statistics.stdev(differences) / math.sqrt(len(pairs))
    else:
        half = math.nan
    wins = [sum(pair.treated.final_wins for pair in pairs), sum(pair.control.final_wins for pair in pairs)]
    episodes = [sum(pair.treated.final_episodes for pair in pairs), sum(pair.control.final_episodes for pair in pairs)]
    pooled_low, pooled_high = newcombe_interval(wins[0], episodes[0], wins[1], episodes[1])
    return PairedSummary(
        pairs=len(pairs), wins=sum(d > 0 for d in differences), ties=sum(d == 0 for d in differences),
        losses=sum(d < 0 for d in differences), mean=mean, low=mean - half, high=mean + half,
        pooled_treated=wins[0] / episodes[0], pooled_control=wins[1] / episodes[1],
        pooled_low=pooled_low, pooled_high=pooled_high,
        treated_interval=wilson_interval(wins[0], episodes[0]), control_interval=wilson_interval(wins[1], episodes[1]),
    )


def setting_name(pair_name: str) -> str:
    """A pair's name less its training seed: the task, demonstrations and settings its seeds share.

    Example:
        >>> setting_name("push_s3_e5_fresh_d2_num_points128")
        'push_e5_fresh_d2_num_points128'
    """
    return re.sub(r"_s\d+(?=_|$)", "", pair_name, count=1)


def paired_t_p_value(differences: list[float]) -> float:
    """Two-sided p-value of Student's t test that the pairs' mean difference is zero; nan with fewer
    than two pairs or none of them differing from the others (no spread to test against)."""
    if len(differences) < 2 or (spread := statistics.stdev(differences)) == 0:
        return math.nan
    t = statistics.fmean(differences) / (spread / math.sqrt(len(differences)))
    return float(2 * student_t.sf(abs(t), len(differences) - 1))


def holm_adjusted(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment of a family of p-values, in their order: the k-th smallest times
    the number not yet passed, never below an earlier one's, at most 1 (a nan counts as 1). Any
    adjusted p under 0.05 holds at 5 % the chance of any false finding in the family."""
    family = [1.0 if math.isnan(value) else value for value in p_values]
    adjusted, running = [1.0] * len(family), 0.0
    for rank, index in enumerate(sorted(range(len(family)), key=family.__getitem__)):
        running = max(running, min(1.0, (len(family) - rank) * family[index]))
        adjusted[index] = running
    return adjusted


def settings_lines(pairs: list[Pair], algo: str, control: str) -> list[str]:
    """Markdown: each setting with two pairs or more (smallest p first), its pairs' summary, the p of
    its paired t test and that p adjusted over every setting tested (Holm). A setting tested alone
    (a replication, say) gets one sentence: its p two-sided and one-sided in the direction of its
    mean, nothing to adjust for; none where no setting has two pairs."""
    groups: dict[str, list[Pair]] = {}
    for pair in pairs:
        groups.setdefault(setting_name(pair.name), []).append(pair)
    tested = {name: group for name, group in groups.items() if len(group) >= 2}
    if len(tested) == 1:
        (name, group), = tested.items()
        p_value = paired_t_p_value([pair.difference for pair in group])
        shown = ("no p (the pairs do not differ from one another)" if math.isnan(p_value) else
                 f"two-sided p = {p_value:.3f}, one-sided in the direction of its mean p = {p_value / 2:.3f}")
        return [f"One setting with two pairs or more ({name}, {len(group)} pairs): Student's paired t test of a "
                f"zero mean difference, {shown}."]
    if not tested:
        return []
    p_values = [paired_t_p_value([pair.difference for pair in group]) for group in tested.values()]
    rows = sorted(zip(tested.items(), p_values, holm_adjusted(p_values), strict=True),
                  key=lambda row: (math.isnan(row[1]), row[1]))
    lines = [f"Per setting (a pair's name less its seed; the {len(tested)} settings with two pairs or more): `{algo}` "
             f"minus `{control}`, Student's paired t test of a zero mean (two-sided p; '-' where the pairs do not "
             f"differ from one another), and that p adjusted for the {len(tested)} settings read together (Holm).", "",
             "| setting | pairs | ahead / level / behind | mean difference (points) [95 %] | p | Holm p |",
             "| --- | --- | --- | --- | --- | --- |"]
    for (name, group), p_value, adjusted in rows:
        summary = summarize_pairs(group)
        shown = "-" if math.isnan(p_value) else f"{p_value:.3f}"
        lines.append(f"| {name} | {summary.pairs} | {summary.wins} / {summary.ties} / {summary.losses} | "
                     f"{signed_points(summary.mean)} [{signed_points(summary.low)}, {signed_points(summary.high)}] | "
                     f"{shown} | {adjusted:.3f} |")
    return lines


def report(pairs: list[Pair], config: PairedConfig) -> str:
    """Markdown: one row per pair (with the reference's cell where asked for), then the summary
    over them, and over those with a reference cell, against it."""
    a, b = f"`{config.algo}`", f"`{config.control}`"
    referenced = against_reference(pairs)
    third = [f"`{config.reference}`"] if referenced else []
    ratios = [(second_cloud_reliance(pair.treated, pair.name, config.runs),
               second_cloud_reliance(pair.control, pair.name, config.runs)) for pair in pairs]
    if all(ratio == (None, None) for ratio in ratios):
        ratios = []  # neither the cells nor the runs hold a perception check: no columns
    reads = [f"{a} second cloud alone x", f"{b} second cloud alone x"] if ratios else []
    columns = ["cell", a, b, "difference (points)", *third, *reads]
    lines = [f"{a} against {b} on the cells they share (final checkpoint; same task, demonstrations, "
             "seed, settings and layouts)", "",
             "| " + " | ".join(columns) + " |", "| " + " | ".join(["---"] * len(columns)) + " |"]
    for index, pair in enumerate(pairs):
        row = [pair.name, _wins(pair.treated), _wins(pair.control), f"{100 * pair.difference:+.0f}"]
        if third:
            row.append(_wins(pair.reference) if pair.reference is not None else "-")
        if ratios:
            row += ["-" if ratio is None else f"{ratio:.1f}" for ratio in ratios[index]]
        lines.append("| " + " | ".join(row) + " |")
    lines += ["", summary_sentence(pairs, config.algo, config.control)]
    if ratios:
        lines += ["", reliance_sentence(pairs, ratios, config.algo, config.control)]
    if referenced:
        lines += ["", f"Against `{config.reference}` on the pairs with its cell: "
                      f"{summary_sentence(referenced, config.algo, config.reference)}"]
    if settings := settings_lines(pairs, config.algo, config.control):
        lines += ["", *settings]
    return "\n".join(lines)


def signed_points(fraction: float) -> str:
    """A difference of success fractions in points, signed, one decimal, never "-0.0"."""
    return f"{round(100 * fraction, 1) + 0.0:+.1f}"


def _wins(cell: Cell) -> str:
    return f"{cell.final_wins}/{cell.final_episodes}"


def summary_sentence(pairs: list[Pair], algo: str, control: str) -> str:
    """One sentence: how many pairs, wins / ties / losses, the mean difference over pairs, the
    pooled episodes' rates (whether their intervals overlap) and difference, each with its 95 %
    interval."""
    summary, a = summarize_pairs(pairs), f"`{algo}`"
    interval = (f"[{signed_points(summary.low)}, {signed_points(summary.high)}] (Student t over pairs)"
                if summary.pairs > 1 else "(one pair: no interval)")
    (treated_low, treated_high), (control_low, control_high) = summary.treated_interval, summary.control_interval
    pooled = (f"{100 * summary.pooled_treated:.1f} % [{100 * treated_low:.1f}-{100 * treated_high:.1f}] against "
              f"{100 * summary.pooled_control:.1f} % [{100 * control_low:.1f}-{100 * control_high:.1f}] (Wilson, "
              f"{'apart' if summary.intervals_apart else 'overlapping'}), difference "
              f"{100 * (summary.pooled_treated - summary.pooled_control):+.1f} "
              f"[{100 * summary.pooled_low:+.1f}, {100 * summary.pooled_high:+.1f}] (Newcombe)")
    plural = "s" if summary.pairs != 1 else ""
    return (f"{summary.pairs} pair{plural} of {a} and `{control}`: {a} ahead in {summary.wins}, level in "
            f"{summary.ties}, behind in {summary.losses}; mean difference {signed_points(summary.mean)} points "
            f"{interval}; pooled episodes {pooled}.")


def plot(pairs: list[Pair], config: PairedConfig, path: str | Path) -> Path:
    """Each pair's difference as a dot with its own Newcombe interval, and the mean over pairs
    with its t interval; zero marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = summarize_pairs(pairs)
    figure, axes = plt.subplots(figsize=(7, 1.2 + 0.32 * (len(pairs) + 1)))
    for row, pair in enumerate(pairs):
        low, high = newcombe_interval(pair.treated.final_wins, pair.treated.final_episodes,
                                      pair.control.final_wins, pair.control.final_episodes)
        below, above = 100 * (pair.difference - low), 100 * (high - pair.difference)
        axes.errorbar(100 * pair.difference, row, xerr=[[below], [above]], fmt="o", color="tab:blue", capsize=2)
    mean_row = len(pairs)
    if summary.pairs > 1:
        axes.errorbar(100 * summary.mean, mean_row, xerr=[[100 * (summary.mean - summary.low)],
                                                          [100 * (summary.high - summary.mean)]],
                      fmt="D", color="black", capsize=3)
    else:
        axes.plot(100 * summary.mean, mean_row, "D", color="black")
    axes.axvline(0, color="grey", linewidth=0.8)
    axes.set_yticks(range(len(pairs) + 1), [pair.name for pair in pairs] + ["mean over pairs"], fontsize=7)
    axes.invert_yaxis()
    axes.set_xlabel(f"{config.algo} minus {config.control}, final-checkpoint success (points)")
    return save_figure(figure, path)


def run(config: PairedConfig) -> list[Pair]:
    pairs = pairs_in(config.results, config.algo, config.control, config.reference, config.tasks, config.demos)
    if not pairs:
        among = f" of {', '.join(config.tasks)}" if config.tasks else ""
        among += f" at {' or '.join(map(str, config.demos))} demonstrations" if config.demos else ""
        raise ValueError(f"no {config.algo} cell{among} in {', '.join(config.results)} has a {config.control} twin")
    text = report(pairs, config)
    print(text)
    if config.plot:
        print(f"plot: {plot(pairs, config, config.plot)}")
    if config.markdown:
        atomic_write_text(Path(config.markdown), markdown_page(text, config))
        print(f"report: {config.markdown}")
    return pairs


def report_page(title: str, command: str, markdown: str, plot: str | None, caption: str, text: str) -> str:
    """A report's text as a markdown page: its title, the command that rewrites it (given
    ``--markdown markdown``), its plot (when drawn, linked from the page's directory) and the text."""
    lines = [f"# {title}", "", f"Written by `{command} --markdown {markdown}`.", ""]
    if plot:
        lines += [f"![{caption}]({os.path.relpath(plot, Path(markdown).parent)})", ""]
    return "\n".join([*lines, text, ""])


def markdown_page(text: str, config: PairedConfig) -> str:
    """``report``'s text as a page: a title, the command that rewrites it, the plot (when drawn)."""
    options = [*(f"--results {directory}" for directory in config.results), f"--algo {config.algo}",
               f"--control {config.control}", *(f"--task {task}" for task in config.tasks),
               *(f"--demos {count}" for count in config.demos),
               *(f"--runs {directory}" for directory in config.runs)]
    if config.reference:
        options.append(f"--reference {config.reference}")
    if config.plot:
        options.append(f"--plot {config.plot}")
    return report_page(f"`{config.algo}` against `{config.control}`, cell by cell",
                       f"d2a bench paired {' '.join(options)}", config.markdown, config.plot,
                       "each pair's difference with its interval; the mean over pairs", text)
