"""Tables of finished policy runs (``d2a report``): success over seeds, with intervals.

Reads what ``d2a train-policy`` stores in each checkpoint (its configuration, the final
evaluation, the perception check) without building the networks. Runs that differ only in
their seed form one row: the success of each seed's final checkpoint, the episodes pooled
into one 95 % Wilson interval, and each seed's reliance ratios (the held-out or training
one-step error with an input shuffled, over the intact error). Rows of the same task and
algorithm are told apart by the settings in which they differ.

Example::

    d2a report runs/hammer/*/s*        # every variant and seed under runs/hammer
    d2a report runs/*/*/s* --plot success.png
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from collectors.evaluation import wilson_interval
from d2a_agents.checkpoint import load_checkpoint
from d2a_agents.policy.checkpoints import CHECKPOINT_NAME
from d2a_agents.policy.perception import Reliance
from d2a_agents.success_plot import SuccessBar, plot_success_bars

# What tells seeds of one configuration apart, not the configuration.
_NOT_SETTINGS = {"seed"}


@dataclass(frozen=True)
class RunOutcome:
    """One run's final evaluation on one task, and its perception check."""

    path: Path
    task: str
    algo: str
    seed: int
    wins: int
    episodes: int
    settings: dict[str, Any]  # policy and training settings, flattened, seed excluded
    reliance: dict[str, float]  # "clouds" / "imagined" / "state" -> shuffled over intact error

    @property
    def rate(self) -> float:
        """Success of the final checkpoint on this task."""
        return self.wins / self.episodes


def _flatten(settings: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in settings.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = list(value) if isinstance(value, tuple) else value
    return flat


def _ratios(record: dict[str, Any]) -> dict[str, float]:
    check = Reliance.from_record(record)
    ratios = {"clouds": check.cloud_ratio, "imagined": check.imagined_ratio, "state": check.state_ratio}
    return {name: ratio for name, ratio in ratios.items() if ratio is not None}


def read_run(path: str | Path) -> list[RunOutcome]:
    """The final evaluation of a run directory (or its checkpoint file), one entry per task;
    empty while the run is still training or when it was not evaluated at its last step
    (``--eval-episodes 0``)."""
    path = Path(path)
    checkpoint = path / CHECKPOINT_NAME if path.is_dir() else path
    payload = load_checkpoint(checkpoint, "policy")
    if payload["step"] < payload["train_config"]["steps"]:
        return []  # an intermediate checkpoint, even where it was evaluated
    final = [point for point in payload.get("history", []) if point["step"] == payload["step"]]
    checks = payload.get("reliance") or []
    reliance = _ratios(checks[-1]) if checks else {}
    run_config = payload["run_config"]
    applied = {"augment_shift": payload["augment_shift"]} if "augment_shift" in payload else {}  # None -> its value
    settings = _flatten({"policy": payload["policy_config"],
                         **{key: value for key, value in run_config.items() if key not in _NOT_SETTINGS}, **applied})
    return [RunOutcome(checkpoint.parent, point["task"], payload["policy_config"]["algo"], run_config["seed"],
                       round(point["success_rate"] * point["episodes"]), point["episodes"], settings, reliance)
            for point in final]


@dataclass(frozen=True)
class ReportRow:
    """Runs of one task, algorithm and settings, over their seeds."""

    task: str
    algo: str
    differs: str  # the settings that tell this row from the others of its task and algo
    runs: tuple[RunOutcome, ...]

    @property
    def pooled(self) -> tuple[float, float, float]:
        """Success pooled over every episode of every seed, with its 95 % Wilson interval."""
        wins, episodes = sum(run.wins for run in self.runs), sum(run.episodes for run in self.runs)
        return (wins / episodes, *wilson_interval(wins, episodes))


def _key(value: Any) -> str:
    """A settings value (or a whole settings dict) as comparable text."""
    return json.dumps(value, sort_keys=True, default=str)


def report_rows(outcomes: list[RunOutcome]) -> list[ReportRow]:
    """Group outcomes into rows (same task, algorithm and settings), seeds in order."""
    groups: dict[tuple[str, str, str], list[RunOutcome]] = {}
    for outcome in outcomes:
        groups.setdefault((outcome.task, outcome.algo, _key(outcome.settings)), []).append(outcome)
    rows = []
    for (task, algo, _), runs in sorted(groups.items()):
        seeds = [run.seed for run in runs]
        if len(set(seeds)) < len(seeds):
            raise ValueError(f"{task} {algo}: two runs with the same settings and seed "
                             f"({', '.join(str(run.path) for run in runs)})")
        siblings = [group[0].settings for (t, a, _), group in groups.items() if (t, a) == (task, algo)]
        differing = sorted(name for name in set().union(*siblings)
                           if len({_key(s.get(name)) for s in siblings}) > 1)
        differs = ", ".join(f"{name}={runs[0].settings.get(name)}" for name in differing) or "-"
        rows.append(ReportRow(task, algo, differs, tuple(sorted(runs, key=lambda run: run.seed))))
    return rows


def format_report(rows: list[ReportRow]) -> str:
    """Markdown: per row, seeds, success per seed, pooled [95 %], and the reliance ratios."""
    lines = ["| task | algo | differs in | seeds | success per seed (%) | pooled % [95 % Wilson] | "
             "clouds shuffled x | imagined alone x | state shuffled x |", "|" + " --- |" * 9]
    for row in rows:
        rate, low, high = row.pooled

        def ratios(name: str, row: ReportRow = row) -> str:
            values = [run.reliance.get(name) for run in row.runs]
            return " / ".join("-" if value is None else f"{value:.1f}" for value in values)

        per_seed = " / ".join(f"{100 * run.rate:.0f}" for run in row.runs)
        episodes = {run.episodes for run in row.runs}
        of = f" (of {episodes.pop()})" if len(episodes) == 1 else ""
        lines.append(f"| {row.task} | {row.algo} | {row.differs} | {' / '.join(str(run.seed) for run in row.runs)} | "
                     f"{per_seed}{of} | {100 * rate:.1f} [{100 * low:.1f}-{100 * high:.1f}] | "
                     f"{ratios('clouds')} | {ratios('imagined')} | {ratios('state')} |")
    return "\n".join(lines)


def report_bars(rows: list[ReportRow]) -> dict[str, dict[str, SuccessBar]]:
    """The rows as bars: per algorithm and settings, per task, pooled success, its 95 %
    interval and each seed's success."""
    bars: dict[str, dict[str, SuccessBar]] = {}
    for row in rows:
        label = row.algo if row.differs == "-" else f"{row.algo} ({row.differs})"
        rate, low, high = row.pooled
        bars.setdefault(label, {})[row.task] = SuccessBar(rate, low, high, tuple(run.rate for run in row.runs))
    return bars


def plot_report(rows: list[ReportRow], path: str | Path) -> Path:
    """Draw :func:`report_bars` of ``rows`` to ``path``."""
    return plot_success_bars(report_bars(rows), path, "final checkpoint, pooled over seeds (95 % Wilson); "
                                                      "dots: seeds")
