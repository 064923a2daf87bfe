"""DAgger on the learnability check: the student acts, the expert labels (Ross et al., 2011).

Round 0 is ``d2a bench experts``' learnability check: the state policy (``imitation_algo``)
trained on ``imitation_demos`` of the expert's demonstrations. Every further round runs the
last student on ``episodes_per_round`` new layouts while the expert labels each state the
student reaches, appends those episodes (failures included) to the data set, and trains a new
student on everything so far, from scratch. Every student is scored on the same
``imitation_episodes`` new layouts. Demonstrations show only the expert's own states; a
student that drifts off them meets states no label covers, and DAgger labels exactly those.
That needs an expert whose action is a function of the state (an open-loop one labels the
same whatever the student did), and it is no guarantee: on Adroit Door the controller's
labels made each round's student worse (docs/environments.md).

Everything lives in ``workdir`` and rerunning the command resumes it: collections append,
training resumes, and each round's score is kept beside its policy.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from benchmarks.experts import (
    IMITATION_SEED,
    ExpertBenchConfig,
    collect_demonstrations,
    evaluate_imitation,
    imitation_acting,
    imitation_paths,
    train_imitation,
)
from collectors.atomic import atomic_write_text
from collectors.collect import CollectConfig, collect
from collectors.evaluation import EvaluationResult, honest_protocol
from collectors.experts import expert_name
from collectors.storage import DemoDataset
from d2a_agents.policy.checkpoints import checkpoint_student

DAGGER_SEED = 10_000  # round r's layouts start at r x this: apart from the demonstrations' and the check's
SCORE_FILE = "dagger_score.json"


@dataclass(frozen=True)
class DaggerConfig:
    """What ``d2a bench dagger`` runs.

    Attributes:
        check: the learnability check it starts from (its task list, expert kind, state
            policy, demonstrations, evaluation layouts, action draws and work directory).
        rounds: rounds after the first student (0: the learnability check alone).
        episodes_per_round: the student's labelled episodes added per round.
    """

    check: ExpertBenchConfig = field(default_factory=lambda: ExpertBenchConfig(
        tasks=("adroit-door",), imitation_demos=10, workers=1, workdir="outputs/bench_dagger"))
    rounds: int = 3
    episodes_per_round: int = 10

    def __post_init__(self) -> None:
        if self.check.imitation_demos < 1:
            raise ValueError("DAgger starts from demonstrations: imitation_demos must be at least 1")
        if self.rounds < 0 or self.episodes_per_round < 1:
            raise ValueError(f"need rounds >= 0 and episodes_per_round >= 1, got {self.rounds}, "
                             f"{self.episodes_per_round}")
        if self.rounds * DAGGER_SEED + self.episodes_per_round > IMITATION_SEED:
            raise ValueError(f"{self.rounds} rounds would reach the check's layouts (seed {IMITATION_SEED})")


@dataclass(frozen=True)
class Round:
    """One student: the labelled episodes it trained on, its score on the check's layouts and,
    from round 1 on, how its predecessor fared on the episodes this round added."""

    index: int
    episodes: int
    run: Path
    score: EvaluationResult
    collected: tuple[int, int] | None = None  # (successes, episodes) of the predecessor while collecting


def run_task(config: DaggerConfig, task: str) -> list[Round]:
    """Every round of ``task``; each student trained and scored once, then read back."""
    check = config.check
    kind = check.settings(task).kind
    data, first_run = imitation_paths(check, task, "_dagger")
    collect_demonstrations(check, task, data)
    rounds: list[Round] = []
    bar = tqdm(range(config.rounds + 1), desc=f"{task} DAgger rounds", disable=not check.progress)
    for index in bar:
        run = first_run.with_name(f"{first_run.name}{index}")
        collected = None
        if index:
            seed = index * DAGGER_SEED
            collect(CollectConfig(
                tasks=(task,), out=str(data), episodes=config.episodes_per_round, seed=seed, append=True,
                env_kwargs=check.env_kwargs, expert=kind, progress=False,
                student=checkpoint_student(rounds[-1].run, task, imitation_acting(check))))
            collected = _collection_successes(data, task, seed)
        episodes = check.imitation_demos + index * config.episodes_per_round
        _check_rounds(data, task, index, episodes)
        rounds.append(Round(index, episodes, run, _score(check, task, data, run, episodes), collected))
        bar.set_postfix(score=f"{100 * rounds[-1].score.success_rate:.0f} %")
    return rounds


def _check_rounds(data: Path, task: str, index: int, episodes: int) -> None:
    """Refuse a data set whose first collections are not the demonstrations and rounds 1 ..
    ``index`` in order, with ``episodes`` episodes in all: the round's student trains on them."""
    metadata = DemoDataset.open(data).metadata
    seeds = [c.seed for c in metadata.collections if c.task == task][: index + 1]
    held = sum(c.kept for c in metadata.collections if c.task == task and c.seed in seeds)
    wanted = [r * DAGGER_SEED for r in range(index + 1)]
    if seeds != wanted or held != episodes:
        raise RuntimeError(f"{data} should begin with {episodes} episodes of {task} from collections of seeds "
                           f"{wanted}, but holds {held} from {seeds}: the "
                           "demonstrations fell short or other settings made it; give the bench another workdir")


def _collection_successes(data: Path, task: str, seed: int) -> tuple[int, int]:
    """(successes, episodes) of the collection of ``task`` started at ``seed`` in ``data``."""
    metadata = DemoDataset.open(data).metadata
    index = next(i for i, c in enumerate(metadata.collections) if c.task == task and c.seed == seed)
    outcomes = [e.success for e in metadata.episodes if e.collection == index]
    return sum(outcomes), len(outcomes)


def _score(check: ExpertBenchConfig, task: str, data: Path, run: Path, episodes: int) -> EvaluationResult:
    """Train the round's student and score it, or read the score it already has."""
    stored = run / SCORE_FILE
    if stored.exists():
        return EvaluationResult(**json.loads(stored.read_text()))
    train_imitation(check, task, data, run, episodes)
    result = evaluate_imitation(check, task, run)
    atomic_write_text(stored, json.dumps(dataclasses.asdict(result)))
    return result


def run(config: DaggerConfig = DaggerConfig()) -> dict[str, list[Round]]:
    """Every task's rounds; prints one markdown table per task and returns the rounds."""
    check = config.check
    results = {}
    for task in check.tasks:
        rounds = run_task(config, task)
        results[task] = rounds
        draws = f", mean of {check.imitation_action_draws} draws" if check.imitation_action_draws > 1 else ""
        expert = expert_name(task, check.settings(task).kind)
        print(f"\nDAgger on {task}: {check.imitation_algo} (cpu preset, training seed 0{draws}), "
              f"the {expert} expert labelling, {config.episodes_per_round} student "
              f"episodes per round (layouts {DAGGER_SEED} x round ...), scored on {check.imitation_episodes} new "
              f"layouts from {IMITATION_SEED}\n")
        print("| round | labelled episodes | the previous student while collecting | score [95 %] |")
        print("| --- | --- | --- | --- |")
        for row in rounds:
            rate, low, high = honest_protocol(row.score.successes)
            collected = "-" if row.collected is None else f"{row.collected[0]}/{row.collected[1]}"
            print(f"| {row.index} | {row.episodes} | {collected} | "
                  f"{100 * rate:.0f} % [{100 * low:.0f}-{100 * high:.0f}] |")
    return results
