"""Success rates as grouped bars: one group per task, one bar per variant, each with its 95 %
interval, and optionally each training seed as a dot and a second figure (the paper's
protocol) as a triangle. Used by ``d2a report --plot`` and ``d2a bench success``.

Example::

    bars = {"mp1": {"push": SuccessBar(0.87, 0.83, 0.90, seeds=(0.86, 0.84, 0.91))}}
    plot_success_bars(bars, "success.png", "final checkpoint, 100 episodes per seed")
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class SuccessBar:
    """One variant on one task: success rate and its interval (fractions in [0, 1])."""

    rate: float
    low: float
    high: float
    seeds: tuple[float, ...] = ()  # per-seed rates, drawn as dots on the bar
    marker: float | None = None  # a second figure for the same cell, drawn as a triangle


def plot_success_bars(bars: dict[str, dict[str, SuccessBar]], path: str | Path, title: str) -> Path:
    """Write grouped bars of ``bars[variant][task]`` (percent, 0-100) to ``path``; a variant
    without a figure on a task leaves a gap there."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not bars:
        raise ValueError("nothing to plot: no variant has a figure")
    tasks = list(dict.fromkeys(task for per_task in bars.values() for task in per_task))
    width = 0.8 / len(bars)
    width_inches = 2.2 + 1.5 * len(tasks) * max(1.0, len(bars) / 4)
    fig, ax = plt.subplots(figsize=(width_inches, 4.0))
    for k, (variant, per_task) in enumerate(bars.items()):
        offset = (k - (len(bars) - 1) / 2) * width
        xs = [i + offset for i, task in enumerate(tasks) if task in per_task]
        cells = [per_task[task] for task in tasks if task in per_task]
        errors = [[100 * (c.rate - c.low) for c in cells], [100 * (c.high - c.rate) for c in cells]]
        drawn = ax.bar(xs, [100 * c.rate for c in cells], width, yerr=errors, capsize=2, label=variant)
        colour = drawn.patches[0].get_facecolor()
        for x, cell in zip(xs, cells, strict=True):
            ax.plot([x] * len(cell.seeds), [100 * s for s in cell.seeds], ".", color="k", markersize=4)
            if cell.marker is not None:
                ax.plot([x], [100 * cell.marker], "v", color=colour, markeredgecolor="k")
    ax.set_xticks(range(len(tasks)), tasks)
    ax.set_ylim(0, 105)
    ax.set_ylabel("success %")
    ax.set_title(textwrap.fill(title, width=int(14 * width_inches)), fontsize=9)  # ~14 characters an inch at 9 pt
    ax.legend(fontsize=7, loc="lower left")
    return save_figure(fig, path)


def save_figure(fig: Any, path: str | Path) -> Path:
    """Lay out, write (making its directory) and close a matplotlib figure; returns ``path``."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")  # long tick labels are never clipped
    plt.close(fig)
    return path
