"""A grid cell's record, and the summaries every grid's report makes of its cells.

A cell is one (task, method, seed) training run's outcome as the grids store it
(``cells/<name>.json``): its periodic evaluations (the paper's protocol), its final checkpoint's
evaluation (the honest protocol), its times and its perception check. Every grid's report reads
cells through this module; ``d2a bench paired`` and ``d2a bench order`` need nothing else of the
grids, so they import no training code.
"""

from __future__ import annotations

import csv
import io
import json
import statistics
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from collectors.evaluation import honest_protocol, paper_protocol
from d2a_agents.policy.perception import Reliance

DEFAULT_DEMOS = 10  # the paper's Table I count; cells of another count carry it in their names


@dataclass
class Cell:
    """The result of one (task, algo, seed) training run.

    ``periodic``: success rate of each evaluation during training, in order (the last one is
    of the final checkpoint). ``final_wins`` / ``final_episodes``: the final checkpoint's
    evaluation (the extra one when ``final_episodes`` > 0, else the last periodic one).
    ``train_seconds``: wall time of the training, periodic evaluations included, summed over
    the calls of a run resumed after interruptions (cells of runs whose checkpoints predate
    that sum hold only the last call's); ``final_seconds``: the
    final evaluation's (``None`` in cells stored before it was recorded). ``demos``: the
    demonstrations it trained on (cells stored before it was recorded trained on 10).
    ``reliance``: the policy's last perception check as its checkpoint stores it (how much each
    input is read: one-step error with that input shuffled), kept with the cell so that the
    mechanism outlives the work directory (``None``: not checked, or stored before it was kept).
    """

    task: str
    algo: str
    seed: int
    periodic: list[float]
    final_wins: int
    final_episodes: int
    train_seconds: float
    final_seconds: float | None = None
    demos: int = DEFAULT_DEMOS
    reliance: dict[str, float | int | str | None] | None = None

    @property
    def paper(self) -> float:
        return paper_protocol(self.periodic)

    @property
    def honest(self) -> float:
        return self.final_wins / self.final_episodes


def read_cell(path: Path) -> Cell:
    return Cell(**json.loads(path.read_text()))


def cells_csv(cells: list[Cell], columns: dict[str, Callable[[Cell], object]] | None = None) -> str:
    """One CSV row per cell: what it ran, both protocols, its final outcomes and times, how much its
    policy reads its clouds and its second cloud (its last perception check: one-step error with
    that input shuffled over the intact one; empty where the cell has none), then the extra
    ``columns`` (name: value of a cell)."""
    columns = columns or {}
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["task", "algo", "seed", "demos", "paper", "honest", "final_wins", "final_episodes",
                     "train_seconds", "final_seconds", "clouds_shuffled_x", "second_cloud_shuffled_x", *columns])
    for cell in cells:
        check = Reliance.from_record(cell.reliance) if cell.reliance is not None else None
        ratios = (check.cloud_ratio, check.imagined_ratio) if check is not None else (None, None)
        writer.writerow([cell.task, cell.algo, cell.seed, cell.demos, f"{cell.paper:.4f}", f"{cell.honest:.4f}",
                         cell.final_wins, cell.final_episodes, f"{cell.train_seconds:.0f}",
                         "" if cell.final_seconds is None else f"{cell.final_seconds:.0f}",
                         *("" if ratio is None else f"{ratio:.2f}" for ratio in ratios),
                         *(value(cell) for value in columns.values())])
    return out.getvalue()


def thread_hours(cells: list[Cell]) -> float:
    """Wall time of the cells' training, periodic and final evaluations, in hours of their one
    thread each: their CPU time on idle cores, more where the cores were shared with other runs."""
    return sum(cell.train_seconds + (cell.final_seconds or 0.0) for cell in cells) / 3600


def progress_line(cells: list[Cell], planned: list[str]) -> str:
    """How many of the grid's cells (``planned``: one method name per planned cell, ``cells``:
    the finished ones among them) are finished and their one-thread hours; then the unfinished
    ones at their method's mean rate so far, or every finished cell's where the method has none
    yet: a `d2a` cell (world model, imagination at every step) costs several `dp3` cells."""
    hours = thread_hours(cells)
    unfinished = Counter(planned) - Counter(cell.algo for cell in cells)
    done = (f"{len(cells)} of {len(planned)} cells finished, {hours:.1f} one-thread hours (wall time of one "
            "thread per cell; beside other runs it exceeds the CPU time)")
    if not cells or not unfinished:
        return done
    rates = []
    for algo, count in unfinished.items():
        measured = [cell for cell in cells if cell.algo == algo] or cells
        rates.append((algo, count, thread_hours(measured) / len(measured)))
    parts = ", ".join(f"{count} `{algo}` x {rate:.2f} h" for algo, count, rate in rates)
    return f"{done}; the other {unfinished.total()} at their method's mean rate: about " \
           f"{sum(count * rate for _, count, rate in rates):.1f} more ({parts})"


@dataclass(frozen=True)
class Summary:
    """One (task, algo) over its seeds: the paper protocol's mean over seeds, and the honest
    protocol on the final checkpoints' episodes pooled over seeds, with its 95 % interval."""

    paper: float
    honest: float
    low: float
    high: float
    seeds: tuple[float, ...] = ()  # each seed's final-checkpoint success, in the cells' order


def summarize(cells: list[Cell]) -> dict[tuple[str, str], Summary]:
    """Per (task, algo), in the order the cells came."""
    summaries = {}
    for key in dict.fromkeys((cell.task, cell.algo) for cell in cells):
        runs = [cell for cell in cells if (cell.task, cell.algo) == key]
        wins, episodes = sum(c.final_wins for c in runs), sum(c.final_episodes for c in runs)
        honest, low, high = honest_protocol([True] * wins + [False] * (episodes - wins))
        summaries[key] = Summary(statistics.fmean(cell.paper for cell in runs), honest, low, high,
                                 tuple(cell.honest for cell in runs))
    return summaries
