"""Finished evaluation episodes kept on disk as they end, so that an interrupted evaluation resumes.

A final evaluation of 100 episodes takes a quarter of an hour on one thread; an evaluation
stopped after its 97th episode should run three more, not a hundred. An
:class:`EpisodeJournal` is a JSON-lines file: its first line is the caller's key (what is
evaluated and how: the policy file's digest, the task, the env's settings), every further line
one finished episode. A journal whose key differs (another policy, other settings) is started
over, and a last line cut short by the interruption is dropped.

Example::

    journal = EpisodeJournal("run/final_evaluation.jsonl", {"policy": digest, "task": "push"})
    evaluate(policy_factory, "push", 100, seed=100_000, journal=journal)  # stopped at episode 97
    evaluate(policy_factory, "push", 100, seed=100_000, journal=EpisodeJournal(...))  # runs 3
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from collectors.atomic import atomic_write_text


@dataclass
class EpisodeRecord:
    """One episode's totals: running while its steps arrive, final once it is done."""

    reward: float = 0.0
    length: int = 0
    success_step: int | None = None


class EpisodeJournal:
    """The episodes an evaluation has finished, by reset seed, on disk and in ``finished``.

    ``seconds``: the evaluation time up to its last recorded episode, summed over the calls
    that wrote it (time spent on an episode the interruption cut is not counted).
    """

    def __init__(self, path: str | Path, key: Mapping[str, Any]) -> None:
        self.path = Path(path)
        self.header = json.dumps({"key": key}, sort_keys=True, default=str)
        self.finished: dict[int, EpisodeRecord] = {}
        self.seconds = 0.0
        lines = self.path.read_text().splitlines() if self.path.exists() else []
        kept: list[str] = []
        for line in lines[1:] if lines[:1] == [self.header] else []:
            try:
                entry = json.loads(line)
            except json.JSONDecodeError:
                break  # the line being written when the evaluation was stopped
            self.finished[entry["seed"]] = EpisodeRecord(entry["reward"], entry["length"], entry["success_step"])
            self.seconds = entry["seconds"]
            kept.append(line)
        if len(kept) != len(lines) - 1:  # new, another key, or a cut line: keep only what holds
            atomic_write_text(self.path, "".join(f"{line}\n" for line in [self.header, *kept]))

    def record(self, seed: int, episode: EpisodeRecord, seconds: float) -> None:
        """Append a finished episode (``seconds``: the evaluation's time so far, all calls)."""
        self.finished[seed], self.seconds = episode, seconds
        with self.path.open("a") as file:
            file.write(json.dumps({"seed": seed, **asdict(episode), "seconds": seconds}) + "\n")
            file.flush()
            os.fsync(file.fileno())
