"""Evaluation speed: a checkpoint's episodes with every step's clouds made, and with only the
steps its policy reads (the default of every evaluation), side by side in one process.

A chunking policy plans every few steps from its last few observations, so most rendered and
imagined clouds were never read. Skipping them must leave every episode as it was: the bench
checks that both settings give the same successes, lengths and returns, and prints the time per
step and episodes per second of each, alternating the order round by round.
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass

import torch

from d2a_agents.policy.checkpoints import evaluate_checkpoint, load_policy
from d2a_envs.gl import software_render_threads

SETTINGS = {"every step": False, "steps read": True}  # name -> skip_unread


@dataclass(frozen=True)
class EvaluationSpeedConfig:
    """What ``d2a bench eval`` measures."""

    policy: str = ""  # policy.pt of d2a train-policy, or its run directory
    task: str = ""
    episodes: int = 5  # per setting and round
    rounds: int = 2
    seed: int = 100_000  # the first layout, as the grids' final evaluations
    threads: int = 1


def run(config: EvaluationSpeedConfig) -> dict[str, list[float]]:
    """Milliseconds per env step of each setting, one entry per round; raises ``AssertionError``
    when the two settings play different episodes."""
    if not (config.policy and config.task):
        raise ValueError("bench eval needs --policy and --task")
    torch.set_num_threads(config.threads)
    software_render_threads(config.threads)
    policy, _ = load_policy(config.policy)
    print(f"{config.task}: {config.policy} ({policy.config.algo}), {config.episodes} episodes x {config.rounds} "
          f"rounds per setting, {config.threads} thread(s); read steps {policy.config.read_steps()}")
    ms_per_step: dict[str, list[float]] = {name: [] for name in SETTINGS}
    episodes_per_second: dict[str, list[float]] = {name: [] for name in SETTINGS}
    for round_index in range(config.rounds):
        names = list(SETTINGS) if round_index % 2 == 0 else list(reversed(SETTINGS))
        results = {name: evaluate_checkpoint(config.policy, config.task, config.episodes, config.seed,
                                             progress=False, end_on_success=True, skip_unread=SETTINGS[name])
                   for name in names}
        first, second = (results[name] for name in SETTINGS)
        assert (first.successes, first.lengths, first.returns) == (second.successes, second.lengths, second.returns), (
            f"round {round_index}: skipping the unread steps changed the episodes")
        for name, result in results.items():
            ms_per_step[name].append(1000 * result.seconds / sum(result.lengths))
            episodes_per_second[name].append(len(result.lengths) / result.seconds)
        print(f"round {round_index + 1}: {sum(first.successes)}/{len(first.successes)} successes, "
              f"{sum(first.lengths)} steps, the same in both settings; "
              + ", ".join(f"{name} {ms_per_step[name][-1]:.1f} ms/step" for name in names))
    print("\n| setting | ms per step, median | episodes per second, median |\n| --- | --- | --- |")
    for name in SETTINGS:
        print(f"| {name} | {statistics.median(ms_per_step[name]):.1f} | "
              f"{statistics.median(episodes_per_second[name]):.3f} |")
    ratios = [every / read for every, read in zip(ms_per_step["every step"], ms_per_step["steps read"], strict=True)]
    print(f"\nevery step / steps read, per round: {', '.join(f'{ratio:.2f}x' for ratio in ratios)}")
    return ms_per_step
