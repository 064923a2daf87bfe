"""Expert success (Meta-World's scripted experts, the Adroit planners) through the D2A env and ``evaluate``.

The experts read the simulator state, so the point clouds are made small (64 px, N = 256):
they cost time and the expert ignores them. For every task below 100 %, the failing
episodes are run again with a longer limit (same seeds, so the same layouts and, the
experts being deterministic, the same first 200 steps) and one that still fails is looked
at (Meta-World): how close the hand got to the object and the object to the goal. With
``imitation_demos``, the learnability check: ``mp1-state`` (the action expert on the simulator
state, so perception plays no part; ``imitation_algo="dp3-state"``: the diffusion expert)
trained on that many of the expert's demonstrations and evaluated on ``imitation_episodes``
new layouts; an expert whose actions are not a function of the state shows a wide gap.
Last, with ``workers`` > 1, the same episodes are evaluated in one process and with ``workers``
processes, side by side.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import statistics
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

import d2a_envs
from collectors.collect import CollectConfig, collect, demonstrations_tag
from collectors.envs import STATE_KEY, make_torchrl_env
from collectors.evaluation import EvaluationResult, evaluate, honest_protocol
from collectors.experts import ExpertSettings, expert_env_kwargs, make_expert
from collectors.ray_jobs import ray_connection
from d2a_agents.policy.agent import STATE_ALGORITHMS
from d2a_agents.policy.checkpoints import Acting, evaluate_checkpoint
from d2a_agents.policy.train import POLICY_PRESETS, TrainPolicyConfig, train_policy
from d2a_envs.tasks import DIFFICULTIES

# Meta-World v3 state layout: hand xyz, gripper opening, first object xyz + quaternion, ...,
# goal xyz in the last three entries.
_HAND, _OBJECT, _GOAL = slice(0, 3), slice(4, 7), slice(36, 39)
_REACHED = 0.05  # metres: the hand "reaches" the object within this distance
IMITATION_SEED = 100_000  # the learnability check's layouts, apart from the expert's and the demonstrations'


@dataclass(frozen=True)
class ExpertBenchConfig:
    """What ``d2a bench experts`` measures.

    Attributes:
        tasks: task names (default: the 50 Meta-World tasks; Adroit tasks are accepted).
        episodes: episodes per task (seeds ``seed .. seed + episodes - 1``).
        seed: seed of the first episode.
        workers: worker processes of each evaluation.
        env_kwargs: point-cloud settings; small, since the expert reads the state.
        max_steps: episode length of the table (DP3/MP1: 200).
        late_max_steps: longer limit used to see whether failures are only late successes.
        speedup_task: task of the one-process vs. ``workers``-process timing.
        speedup_episodes: episode counts of that timing (the worker start-up is amortised
            over more episodes).
        progress: progress bar over tasks.
        ray_address: evaluate on Ray (``"local"``, ``"auto"`` or a cluster address); the
            one-process vs. ``workers``-process timing stays local.
    """

    tasks: tuple[str, ...] = tuple(spec.name for spec in d2a_envs.list_tasks(suite="metaworld"))
    episodes: int = 5
    seed: int = 0
    workers: int = 2
    env_kwargs: dict[str, Any] = field(default_factory=lambda: {"image_size": 64, "num_points": 256})
    max_steps: int = d2a_envs.DEFAULT_MAX_EPISODE_STEPS
    late_max_steps: int = 500
    speedup_task: str = "hammer"
    speedup_episodes: tuple[int, ...] = (5, 20)
    progress: bool = True
    ray_address: str | None = None
    imitation_demos: int = 0  # 0: no learnability check
    imitation_episodes: int = 100
    imitation_dart_noise: float = 0.0  # DART noise of the check's collection (0: plain demonstrations)
    imitation_steps: int = POLICY_PRESETS["cpu"].steps
    imitation_action_draws: int = 1  # chunks drawn per plan, acted on as their mean (d2a eval --action-draws)
    imitation_algo: str = "mp1-state"  # the check's state policy: a privileged-state reference of policy.agent
    workdir: str = "outputs/bench_experts"  # the check's demonstrations and policies
    expert: str | None = None  # the Adroit expert kind (controller, planner); None: each task's default

    def __post_init__(self) -> None:
        if self.imitation_algo not in STATE_ALGORITHMS:
            raise ValueError(f"imitation_algo must be a state policy, one of {list(STATE_ALGORITHMS)}; "
                             f"got {self.imitation_algo!r}")
        ExpertSettings(kind=self.expert)  # an unknown kind fails here

    def settings(self, task: str) -> ExpertSettings:
        """The expert of ``task``: ``expert`` on an Adroit task; Meta-World tasks have one scripted expert."""
        return ExpertSettings(kind=self.expert if d2a_envs.get_task(task).suite == "adroit" else None)


def imitation_success(config: ExpertBenchConfig, task: str) -> EvaluationResult:
    """``imitation_algo`` (``mp1-state``; ``dp3-state``: the diffusion expert) trained (``cpu``
    preset, one thread) on ``imitation_demos`` of the expert's demonstrations of ``task``
    (collected with ``imitation_dart_noise``), its final checkpoint on ``imitation_episodes``
    new layouts, acting on the mean of ``imitation_action_draws``."""
    data, run = imitation_paths(config, task)
    collect_demonstrations(config, task, data)
    train_imitation(config, task, data, run, config.imitation_demos)
    return evaluate_imitation(config, task, run)


def imitation_paths(config: ExpertBenchConfig, task: str, suffix: str = "") -> tuple[Path, Path]:
    """The check's data set and policy run for ``task`` in ``workdir``, named by the
    demonstrations' tag (DART noise, expert kind) and ``suffix``."""
    tag = demonstrations_tag(config.imitation_dart_noise, config.settings(task).kind) + suffix
    workdir = Path(config.workdir)
    return (workdir / "data" / f"{task}{tag}",
            workdir / "runs" / f"{task}_{config.imitation_algo}_d{config.imitation_demos}{tag}")


def collect_demonstrations(config: ExpertBenchConfig, task: str, data: Path) -> None:
    """The check's ``imitation_demos`` demonstrations of ``task`` in ``data`` (resumes)."""
    collect(CollectConfig(tasks=(task,), out=str(data), episodes=config.imitation_demos, append=True,
                          env_kwargs=config.env_kwargs, dart_noise=config.imitation_dart_noise,
                          expert=config.settings(task).kind, progress=False))


def train_imitation(config: ExpertBenchConfig, task: str, data: Path, run: Path, episodes: int) -> None:
    """Train (or resume) the check's state policy on the first ``episodes`` episodes of ``data``."""
    preset = POLICY_PRESETS["cpu"]
    train_policy(TrainPolicyConfig.from_preset(
        preset, data=str(data), out=str(run), policy=dataclasses.replace(preset.policy, algo=config.imitation_algo),
        steps=config.imitation_steps, demos=episodes, eval_episodes=0, threads=1, progress=False))


def evaluate_imitation(config: ExpertBenchConfig, task: str, run: Path) -> EvaluationResult:
    """The final checkpoint of ``run`` on the check's ``imitation_episodes`` new layouts."""
    return evaluate_checkpoint(run, task, config.imitation_episodes, IMITATION_SEED, workers=config.workers,
                               end_on_success=True, progress=False, ray_address=config.ray_address,
                               acting=imitation_acting(config))


def imitation_acting(config: ExpertBenchConfig) -> Acting:
    """How the check's policy acts when scored (and, in ``bench dagger``, when it drives)."""
    return Acting(action_draws=config.imitation_action_draws)


def _expert(config: ExpertBenchConfig, task: str) -> functools.partial:
    return functools.partial(make_expert, task, config.settings(task))


def _env_kwargs(config: ExpertBenchConfig, task: str) -> dict[str, Any]:
    return {**config.env_kwargs, **expert_env_kwargs(task)}


def _distances(task: str, seed: int, config: ExpertBenchConfig) -> str:
    """Roll out episode ``seed`` for ``late_max_steps`` in this process and describe how
    close the hand came to the object and the object to the goal."""
    env = make_torchrl_env(task, {**config.env_kwargs, "max_episode_steps": config.late_max_steps}, seed=seed)
    with contextlib.closing(env), torch.no_grad():
        rollout = env.rollout(config.late_max_steps, make_expert(task, config.settings(task)))
    assert int(rollout["episode_seed"][0]) == seed
    state = torch.cat([rollout[STATE_KEY][:1], rollout["next", STATE_KEY]])
    hand, obj, goal = state[:, _HAND], state[:, _OBJECT], state[:, _GOAL]
    if bool((obj == 0).all()):
        return f"hand comes within {100 * float((hand - goal).norm(dim=-1).min()):.1f} cm of the goal"
    reach = float((hand - obj).norm(dim=-1).min())
    to_goal = float((obj - goal).norm(dim=-1).min())
    start = float((obj[0] - goal[0]).norm())
    if reach > _REACHED:
        return f"hand never within {100 * _REACHED:.0f} cm of the object (closest {100 * reach:.1f} cm)"
    return (
        f"hand reaches the object ({100 * reach:.1f} cm) but the object gets no closer than "
        f"{100 * to_goal:.1f} cm to the goal (from {100 * start:.1f} cm)"
    )


def failure_reason(result: EvaluationResult, config: ExpertBenchConfig) -> str:
    """One line on why the expert failed: late successes, else the distances of one failure."""
    failed = [seed for seed, success in zip(result.seeds, result.successes, strict=True) if not success]
    late_steps = {  # the failed episodes alone, one at a time
        seed: evaluate(_expert(config, result.task), result.task, 1, seed, _env_kwargs(config, result.task),
                       max_steps=config.late_max_steps, progress=False, ray_address=config.ray_address).success_steps[0]
        for seed in failed
    }
    parts = []
    succeeded_late = {seed: late_steps[seed] for seed in failed if late_steps[seed] is not None}
    if succeeded_late:
        steps = ", ".join(f"seed {seed} at step {step}" for seed, step in succeeded_late.items())
        parts.append(f"late success within {config.late_max_steps} steps ({steps})")
    never = [seed for seed in failed if late_steps[seed] is None]
    if never:
        seeds = f"seed(s) {', '.join(map(str, never))} fail even in {config.late_max_steps} steps"
        if d2a_envs.get_task(result.task).suite == "metaworld":  # the distances read Meta-World's state layout
            seeds += f"; seed {never[0]}: {_distances(result.task, never[0], config)}"
        parts.append(seeds)
    return "; ".join(parts)


def speedup(config: ExpertBenchConfig) -> list[dict[str, object]]:
    """Time the same episodes of ``speedup_task`` in one process and in ``workers``."""
    rows = []
    for episodes in config.speedup_episodes:
        task = config.speedup_task
        kwargs = dict(env_kwargs=_env_kwargs(config, task), max_steps=config.max_steps, progress=False)
        single = evaluate(_expert(config, task), task, episodes, config.seed, workers=1, **kwargs)
        parallel = evaluate(_expert(config, task), task, episodes, config.seed, workers=config.workers, **kwargs)
        same = single.successes == parallel.successes and single.returns == parallel.returns
        rows.append(dict(episodes=episodes, single=single.seconds, parallel=parallel.seconds, same=same))
    return rows


def run(config: ExpertBenchConfig = ExpertBenchConfig()) -> list[dict[str, object]]:
    """Evaluate the expert on every task; prints markdown tables and returns the rows."""
    with ray_connection(config.ray_address):  # one Ray connection for every task's evaluation
        return _run(config)


def _run(config: ExpertBenchConfig) -> list[dict[str, object]]:
    rows: list[dict[str, object]] = []
    results: list[EvaluationResult] = []
    for task in tqdm(config.tasks, desc="tasks", disable=not config.progress):
        result = evaluate(
            _expert(config, task), task, config.episodes, config.seed, _env_kwargs(config, task),
            workers=config.workers, max_steps=config.max_steps, progress=False, ray_address=config.ray_address,
        )
        results.append(result)
        steps = [step for step in result.success_steps if step is not None]
        imitation = imitation_success(config, task) if config.imitation_demos else None
        rows.append(dict(
            task=result.task, difficulty=d2a_envs.get_task(task).difficulty or "-",
            successes=sum(result.successes), episodes=result.episodes, rate=result.success_rate,
            mean_return=result.mean_return, median_step=statistics.median(steps) if steps else None,
            seconds=result.seconds, imitation=imitation,
        ))

    last_seed = config.seed + config.episodes - 1
    print(
        f"\nExperts, {config.episodes} episodes per task (seeds {config.seed}..{last_seed}),"
        f" {config.max_steps} steps, env {config.env_kwargs}, {config.workers} workers"
        f"{f', Adroit expert: {config.expert}' if config.expert else ''}\n"
    )
    draws = f", mean of {config.imitation_action_draws} draws" if config.imitation_action_draws > 1 else ""
    imitation_header = (f" {config.imitation_algo} on {config.imitation_demos} demonstrations{draws} [95 %] "
                        "| of the expert's |"
                        if config.imitation_demos else "")
    print("| task | difficulty | success | mean return | median first-success step |" + imitation_header)
    print("| --- | --- | --- | --- | --- |" + (" --- | --- |" if config.imitation_demos else ""))
    for row in rows:
        step = "-" if row["median_step"] is None else f"{row['median_step']:g}"
        imitation = ""
        if row["imitation"] is not None:
            rate, low, high = honest_protocol(row["imitation"].successes)
            share = f"{100 * rate / row['rate']:.0f} %" if row["rate"] else "-"
            imitation = f" {100 * rate:.0f} % [{100 * low:.0f}-{100 * high:.0f}] | {share} |"
        print(
            f"| {row['task']} | {row['difficulty']} | {row['successes']}/{row['episodes']} = {100 * row['rate']:.0f} % "
            f"| {row['mean_return']:.1f} | {step} |" + imitation
        )
    all_outcomes = [success for result in results for success in result.successes]
    mean, low, high = honest_protocol(all_outcomes)
    print(
        f"\nall tasks: {sum(all_outcomes)}/{len(all_outcomes)} episodes = {100 * mean:.1f} % "
        f"(95 % Wilson {100 * low:.1f}-{100 * high:.1f} %); "
        f"evaluation time {sum(row['seconds'] for row in rows):.0f} s"
    )
    for level in DIFFICULTIES:
        outcomes = [s for row, r in zip(rows, results, strict=True) if row["difficulty"] == level for s in r.successes]
        if outcomes:
            print(f"  {level}: {100 * sum(outcomes) / len(outcomes):.1f} % of {len(outcomes)} episodes")

    below = [result for result in results if result.success_rate < 1.0]
    print(f"\nTasks below 100 % ({len(below)}):")
    for result in below:
        print(f"- {result.task} ({sum(result.successes)}/{result.episodes}): {failure_reason(result, config)}")
    if not below:
        print("- none")

    if config.workers > 1:
        _print_speedup(config)
    return rows


def _print_speedup(config: ExpertBenchConfig) -> None:
    """The one-process against ``workers``-process timing, as a markdown table."""
    load = os.getloadavg()[0]
    timing = speedup(config)
    print(
        f"\nParallel evaluation, {config.speedup_task}, {config.max_steps} steps per episode (wall time, worker "
        f"start-up and shutdown included; measured one after the other in this run; {os.cpu_count()} cores, "
        f"1-min load average {load:.1f} before, {os.getloadavg()[0]:.1f} after)\n"
    )
    print(f"| episodes | 1 process (s) | {config.workers} processes (s) | speed-up | identical results |")
    print("| --- | --- | --- | --- | --- |")
    for row in timing:
        print(
            f"| {row['episodes']} | {row['single']:.1f} | {row['parallel']:.1f} | "
            f"{row['single'] / row['parallel']:.2f}x | {row['same']} |"
        )


if __name__ == "__main__":
    run()
