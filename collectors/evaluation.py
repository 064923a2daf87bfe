"""Evaluate a policy on a D2A task through TorchRL, and the two ways of reporting the result.

``evaluate`` runs whole episodes and returns per-episode success and return. Episode k of an
evaluation with seed s is reset with seed s + k (:class:`~d2a_envs.wrappers.SeedEachReset`),
so the set of episodes does not depend on how many worker processes ran them.

Reporting:

* :func:`paper_protocol`: the number DP3 and MP1 publish, the mean of the 5 best evaluation
  success rates seen during training (each evaluation: 20 episodes). It picks the best
  checkpoints after the fact, so it is biased upwards.
* :func:`honest_protocol`: the final checkpoint only, on many episodes (>= 100 recommended),
  with a 95 % Wilson score interval.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any

import torch
from scipy.stats import binomtest
from tensordict import TensorDictBase
from torchrl.collectors import Collector, MultiSyncCollector
from torchrl.envs import EnvBase, InitTracker
from torchrl.envs.utils import ExplorationType
from tqdm import tqdm

import d2a_envs
from collectors.envs import make_torchrl_env
from collectors.episode_journal import EpisodeJournal, EpisodeRecord
from collectors.ray_jobs import JobsLost, Lost, as_completed


@dataclass
class EvaluationResult:
    """Outcome of :func:`evaluate`, one entry per episode, in episode-seed order.

    Attributes:
        task: short task name.
        successes: whether ``success`` was true at any step of the episode (DP3/MP1 convention).
        returns: sum of the episode's rewards (up to its success when ``ended_on_success``).
        seeds: the reset seed of each episode (seed, seed + 1, ...).
        success_steps: 1-based step at which ``success`` first became true, ``None`` if never.
        lengths: steps in each episode.
        workers: worker processes used (1: in this process; on Ray: the number of jobs).
        seconds: wall time of the whole evaluation, worker start-up included.
        ended_on_success: episodes ended at their first success (success counts are unchanged).
    """

    task: str
    successes: list[bool]
    returns: list[float]
    seeds: list[int]
    success_steps: list[int | None] = field(default_factory=list)
    lengths: list[int] = field(default_factory=list)
    workers: int = 1
    seconds: float = 0.0
    ended_on_success: bool = False

    @property
    def episodes(self) -> int:
        return len(self.successes)

    @property
    def success_rate(self) -> float:
        return sum(self.successes) / len(self.successes) if self.successes else float("nan")

    @property
    def mean_return(self) -> float:
        return sum(self.returns) / len(self.returns) if self.returns else float("nan")

    def summary(self) -> str:
        """One line: success rate with its 95 % Wilson interval, mean return, seeds, time."""
        _, low, high = honest_protocol(self.successes)
        seeds = f"{self.seeds[0]}..{self.seeds[-1]}" if len(self.seeds) > 1 else f"{self.seeds[0]}"
        return (
            f"{self.task}: success {sum(self.successes)}/{self.episodes} = {100 * self.success_rate:.1f} % "
            f"(95 % Wilson {100 * low:.1f}-{100 * high:.1f} %), mean return {self.mean_return:.1f}"
            f"{' up to success' if self.ended_on_success else ''}, "
            f"seeds {seeds}, {self.workers} worker(s), {self.seconds:.1f} s"
        )


def _make_eval_env(task: str, env_kwargs: dict[str, Any], seed: int, end_on_success: bool = False) -> EnvBase:
    """The env of one worker: its episodes use seed, seed + 1, ...; also seeds torch's global
    generator (stochastic policies sample from it) and adds ``is_init`` (:class:`InitTracker`).

    Module-level so that spawned workers can unpickle it.
    """
    torch.manual_seed(seed)
    env = make_torchrl_env(task, env_kwargs, seed=seed, end_on_success=end_on_success)
    env.append_transform(InitTracker())
    return env


class _EpisodeTally:
    """Turns collector batches into per-episode results, keeping only the wanted episode seeds.

    Each worker's rows are read on their own and episodes are told apart by ``episode_seed``,
    so neither the order in which workers deliver nor the extra episodes a worker runs past
    its share change the result.
    """

    def __init__(self, wanted: Sequence[Sequence[int]],
                 on_finish: Callable[[int, EpisodeRecord], None] | None = None) -> None:
        self.wanted = [set(seeds) for seeds in wanted]  # per worker
        self.running: list[dict[int, EpisodeRecord]] = [{} for _ in wanted]
        self.finished: dict[int, EpisodeRecord] = {}
        self.on_finish = on_finish  # called with each episode as it finishes

    @property
    def complete(self) -> bool:
        return all(seeds <= self.finished.keys() for seeds in self.wanted)

    def add(self, batch: TensorDictBase) -> int:
        """Read a ``[T]`` (one worker) or ``[workers, T]`` batch; returns episodes finished."""
        rows = batch.unsqueeze(0) if batch.ndim == 1 else batch
        before = len(self.finished)
        for worker, row in enumerate(rows.unbind(0)):
            self._add_row(worker, row)
        return len(self.finished) - before

    def _add_row(self, worker: int, row: TensorDictBase) -> None:
        seeds = row.get("episode_seed").reshape(-1)
        rewards = row.get(("next", "reward")).reshape(-1).double()
        successes = row.get(("next", "success")).reshape(-1)
        dones = row.get(("next", "done")).reshape(-1)
        start = 0
        for seed, count in zip(*torch.unique_consecutive(seeds, return_counts=True), strict=True):
            seed, stop = int(seed), start + int(count)
            if seed > max(self.wanted[worker]) and not self.wanted[worker] <= self.finished.keys():
                missing = sorted(self.wanted[worker] - self.finished.keys())
                raise RuntimeError(f"worker {worker} reached episode seed {seed} without finishing {missing}")
            if seed in self.wanted[worker] and seed not in self.finished:
                episode = self.running[worker].setdefault(seed, EpisodeRecord())
                hits = successes[start:stop].nonzero()
                if episode.success_step is None and len(hits):
                    episode.success_step = episode.length + int(hits[0]) + 1
                episode.reward += float(rewards[start:stop].sum())
                episode.length += stop - start
                if dones[stop - 1]:
                    self.finished[seed] = self.running[worker].pop(seed)
                    if self.on_finish is not None:
                        self.on_finish(seed, self.finished[seed])
            start = stop


def _split(seeds: list[int], workers: int) -> list[list[int]]:
    """Contiguous blocks of seeds, as even as possible: worker i starts at its block's first."""
    size, extra = divmod(len(seeds), workers)
    blocks, start = [], 0
    for worker in range(workers):
        stop = start + size + (worker < extra)
        blocks.append(seeds[start:stop])
        start = stop
    return blocks


def evaluate(
    policy_factory: Callable[[], Callable[[TensorDictBase], TensorDictBase]],
    task: str,
    episodes: int,
    seed: int,
    env_kwargs: dict[str, Any] | None = None,
    workers: int = 1,
    max_steps: int = d2a_envs.DEFAULT_MAX_EPISODE_STEPS,
    progress: bool = True,
    end_on_success: bool = False,
    ray_address: str | None = None,
    episodes_per_job: int = 10,
    journal: EpisodeJournal | None = None,
) -> EvaluationResult:
    """Run ``episodes`` complete episodes of ``task`` with a fresh policy from ``policy_factory``.

    Args:
        policy_factory: zero-argument, picklable callable returning a TensorDict policy that
            reads the env's keys and writes ``action``, e.g. ``functools.partial(ScriptedExpert,
            "hammer")``. Every worker builds its own policy.
        task: task name or env id (``hammer``, ``D2A-MetaWorld-Hammer-v0``).
        episodes: number of episodes; episode k is reset with seed ``seed + k``.
        seed: seed of the first episode.
        env_kwargs: point-cloud settings passed to ``gym.make`` (``image_size``, ``num_points``, ...).
        workers: 1 runs a :class:`~torchrl.collectors.Collector` in this process; more runs a
            :class:`~torchrl.collectors.MultiSyncCollector` with that many spawned processes
            (capped at ``episodes``), worker i taking the i-th contiguous block of seeds.
        max_steps: steps per episode (the env's time limit; DP3/MP1: 200).
        progress: show a progress bar over episodes.
        end_on_success: end each episode at its first success: the same success verdicts in
            less time (a successful policy's episodes are shorter); returns stop there.
        ray_address: run on Ray instead (``"local"``, ``"auto"`` or a cluster address, see
            :func:`~collectors.ray_jobs.ray_cluster`): blocks of ``episodes_per_job`` episodes
            become Ray jobs of one CPU each; ``workers`` is then unused. The policy factory
            (a checkpoint path in it) must be readable on every node.
        episodes_per_job: episodes of one Ray job (each job builds its env and policy once).
        journal: keep each finished episode on disk as it ends, and run only the episodes the
            journal does not hold yet, so that an evaluation stopped part-way resumes where it
            was (local evaluations only; ``seconds`` then counts the earlier calls' time too).

    Reproducibility: each episode's layout (and point-cloud sampling) depends on its seed
    only, so for a deterministic policy (the scripted experts, a network in eval mode with
    deterministic sampling) the results are identical for any ``workers``. torch's global
    generator is seeded in each worker with the first seed of its block (in this process
    under :func:`torch.random.fork_rng`, so the caller's generator is left alone): a policy
    that samples from it (diffusion / flow noise) gets identical results for the same
    ``(seed, workers)``, but different ones when ``workers`` changes or a journal resumes,
    unless it reseeds itself per episode from ``episode_seed``. numpy's global generator is not
    seeded.

    The D2A policies and experts reseed their sampling from ``episode_seed`` at every episode
    start, so their per-episode outcomes are the same for any ``workers``, on Ray and resumed.

    Stateful policies (e.g. an observation history): the policy sees every step of an
    episode in order, in the process that built it, and episodes follow one another; it
    should clear its state on the first step of an episode, which carries ``is_init = True``
    (the env has an :class:`~torchrl.envs.InitTracker`); ``episode_seed`` changes there too.
    TorchRL's collector also calls the policy once when it is built, on the first reset's
    tensordict (``is_init`` true), to find its output keys: count episodes with ``is_init``,
    not calls.

    Returns:
        An :class:`EvaluationResult` in episode-seed order.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be positive, got {episodes}")
    if workers < 1:
        raise ValueError(f"workers must be positive, got {workers}")
    if max_steps < 1:
        raise ValueError(f"max_steps must be positive, got {max_steps}")
    env_kwargs = dict(env_kwargs or {})
    if "max_episode_steps" in env_kwargs:
        raise ValueError("pass the episode length as max_steps, not as env_kwargs['max_episode_steps']")
    if episodes_per_job < 1:
        raise ValueError(f"episodes_per_job must be positive, got {episodes_per_job}")
    name = d2a_envs.get_task(task).name  # fails early on unknown names
    seeds = list(range(seed, seed + episodes))
    if ray_address is not None:
        if journal is not None:
            raise ValueError("a journal keeps local evaluations only (Ray retries its lost jobs itself)")
        return _evaluate_on_ray(policy_factory, name, seeds, env_kwargs, max_steps, progress, end_on_success,
                                ray_address, episodes_per_job)
    env_kwargs["max_episode_steps"] = max_steps
    workers = min(workers, episodes)
    done = dict(journal.finished) if journal is not None else {}
    earlier = journal.seconds if journal is not None else 0.0
    bar = tqdm(total=episodes, initial=sum(s in done for s in seeds), desc=f"eval {name}", unit="ep",
               disable=not progress)
    start = time.perf_counter()

    def finish(seed: int, episode: EpisodeRecord) -> None:
        done[seed] = episode
        if journal is not None:
            journal.record(seed, episode, earlier + time.perf_counter() - start)

    threads = torch.get_num_threads()  # the multi-process collector lowers this process's count
    try:
        for run in _consecutive_runs([s for s in seeds if s not in done]):
            _run_episodes(policy_factory, name, run, env_kwargs, min(workers, len(run)), end_on_success,
                          finish, bar)
    finally:
        bar.close()
        torch.set_num_threads(threads)
    results = [done[s] for s in seeds]
    return EvaluationResult(
        task=name,
        successes=[episode.success_step is not None for episode in results],
        returns=[episode.reward for episode in results],
        seeds=seeds,
        success_steps=[episode.success_step for episode in results],
        lengths=[episode.length for episode in results],
        workers=workers,
        seconds=earlier + time.perf_counter() - start,
        ended_on_success=end_on_success,
    )


def _consecutive_runs(seeds: list[int]) -> list[list[int]]:
    """Sorted seeds cut where they skip one: each run is one env's consecutive resets."""
    runs: list[list[int]] = []
    for seed in seeds:
        if runs and seed == runs[-1][-1] + 1:
            runs[-1].append(seed)
        else:
            runs.append([seed])
    return runs


def _run_episodes(
    policy_factory: Callable[[], Callable[[TensorDictBase], TensorDictBase]], task: str, seeds: list[int],
    env_kwargs: dict[str, Any], workers: int, end_on_success: bool,
    on_finish: Callable[[int, EpisodeRecord], None], bar: tqdm,
) -> None:
    """Run the episodes of consecutive ``seeds``, worker i its i-th block, each one handed to
    ``on_finish`` as it ends."""
    blocks = _split(seeds, workers)
    tally = _EpisodeTally(blocks, on_finish)
    frames = env_kwargs["max_episode_steps"]
    if workers == 1:
        with torch.random.fork_rng(devices=[]):
            env = _make_eval_env(task, env_kwargs, blocks[0][0], end_on_success)
            collector = Collector(
                env, policy_factory=policy_factory, frames_per_batch=frames, total_frames=-1,
                exploration_type=ExplorationType.DETERMINISTIC, auto_register_policy_transforms=False,
            )
            _drain(collector, tally, bar)
    else:
        collector = MultiSyncCollector(
            [partial(_make_eval_env, task, env_kwargs, block[0], end_on_success) for block in blocks],
            policy_factory=policy_factory, frames_per_batch=workers * frames, total_frames=-1,
            cat_results="stack", exploration_type=ExplorationType.DETERMINISTIC,
            auto_register_policy_transforms=False,
        )
        _drain(collector, tally, bar)


def _evaluate_block(
    policy_factory: Callable[[], Callable[[TensorDictBase], TensorDictBase]], task: str, seeds: list[int],
    env_kwargs: dict[str, Any], max_steps: int, end_on_success: bool,
) -> EvaluationResult:
    """One Ray job: consecutive episodes in the worker's process (module-level: Ray imports it)."""
    return evaluate(policy_factory, task, len(seeds), seeds[0], env_kwargs, workers=1, max_steps=max_steps,
                    progress=False, end_on_success=end_on_success)


def _evaluate_on_ray(
    policy_factory: Callable[[], Callable[[TensorDictBase], TensorDictBase]], task: str, seeds: list[int],
    env_kwargs: dict[str, Any], max_steps: int, progress: bool, end_on_success: bool, address: str,
    episodes_per_job: int,
) -> EvaluationResult:
    """:func:`evaluate` as Ray jobs of ``episodes_per_job`` episodes, merged in seed order."""
    blocks = [seeds[start:start + episodes_per_job] for start in range(0, len(seeds), episodes_per_job)]
    jobs = [(policy_factory, task, block, env_kwargs, max_steps, end_on_success) for block in blocks]
    start = time.perf_counter()
    parts: dict[int, EvaluationResult] = {}
    lost: list[int] = []
    with tqdm(total=len(seeds), desc=f"eval {task} on Ray", unit="ep", disable=not progress) as bar:
        for index, outcome in as_completed(_evaluate_block, jobs, address):
            if isinstance(outcome, Lost):
                lost.extend(blocks[index])
            else:
                parts[index] = outcome
            bar.update(len(blocks[index]))
    if lost:
        raise JobsLost(f"{task}: the Ray workers of episode seeds {sorted(lost)} died on every attempt; "
                           "their episodes are missing (the others finished)")
    done = [parts[index] for index in range(len(blocks))]
    return EvaluationResult(
        task=task,
        successes=[s for part in done for s in part.successes],
        returns=[r for part in done for r in part.returns],
        seeds=seeds,
        success_steps=[s for part in done for s in part.success_steps],
        lengths=[n for part in done for n in part.lengths],
        workers=len(blocks),
        seconds=time.perf_counter() - start,
        ended_on_success=end_on_success,
    )


def _drain(collector: Collector | MultiSyncCollector, tally: _EpisodeTally, bar: tqdm) -> None:
    """Feed batches to ``tally`` until every wanted episode is finished, then stop the workers."""
    try:
        for batch in collector:
            bar.update(tally.add(batch))
            if tally.complete:
                break
    finally:
        collector.shutdown()


def paper_protocol(evaluation_success_rates: Sequence[float], top_k: int = 5) -> float:
    """The success rate DP3 and MP1 report for one training run: the mean of the ``top_k``
    best evaluation success rates seen during training.

    Each entry is one evaluation of a checkpoint (in the papers: 20 episodes, every fixed
    number of epochs); the papers then average this number over 3 training seeds. With
    fewer than ``top_k`` evaluations, all of them are averaged. The choice of the best
    checkpoints uses the evaluation episodes themselves, so the number is optimistic; see
    :func:`honest_protocol`.
    """
    rates = [float(rate) for rate in evaluation_success_rates]
    if not rates:
        raise ValueError("paper_protocol needs at least one evaluation success rate")
    if top_k < 1:
        raise ValueError(f"top_k must be positive, got {top_k}")
    if any(not 0.0 <= rate <= 1.0 for rate in rates):
        raise ValueError(f"success rates must lie in [0, 1], got {rates}")
    best = sorted(rates, reverse=True)[:top_k]
    return sum(best) / len(best)


def wilson_interval(successes: int, trials: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion: ``successes`` out of ``trials`` (scipy's)."""
    if trials < 1:
        raise ValueError(f"trials must be positive, got {trials}")
    if not 0 <= successes <= trials:
        raise ValueError(f"successes must lie in [0, {trials}], got {successes}")
    interval = binomtest(successes, trials).proportion_ci(confidence_level=confidence, method="wilson")
    return float(interval.low), float(interval.high)


def honest_protocol(successes: Sequence[bool]) -> tuple[float, float, float]:
    """Success rate of the final checkpoint with its 95 % Wilson score interval.

    ``successes`` are the per-episode outcomes of one evaluation of the last checkpoint
    (e.g. :attr:`EvaluationResult.successes`); use >= 100 episodes: with 20 the interval
    is about +-20 points wide. Returns ``(mean, low, high)``.
    """
    outcomes = [bool(success) for success in successes]
    if not outcomes:
        raise ValueError("honest_protocol needs at least one episode")
    wins = sum(outcomes)
    low, high = wilson_interval(wins, len(outcomes))
    return wins / len(outcomes), low, high
