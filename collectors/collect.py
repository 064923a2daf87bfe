"""Collect expert demonstrations with a TorchRL ``Collector`` into a data set on disk.

The experts: Meta-World's scripted policies, the Adroit planners (:mod:`collectors.adroit_experts`).

Episode k of a collection with seed s is reset with seed s + k, so every stored episode is
reproducible on its own, and a killed collection resumes exactly where it stopped: re-run
the same command with ``--append`` and the attempts already made are skipped.

On Ray (``ray_address``), the attempts run in parallel as Ray jobs, one episode each, and
are stored in seed order: the same episodes, in the same order, as a local collection.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import InitTracker
from tqdm import tqdm

import d2a_envs
from collectors.atomic import exclusive_writer, holds_only_lock
from collectors.envs import make_torchrl_env
from collectors.experts import ExpertSettings, Student, expert_env_kwargs, expert_name, make_expert
from collectors.ray_jobs import JobsLost, Lost, as_completed, ray_connection
from collectors.storage import (
    CollectionRecord,
    DatasetError,
    DemoDataset,
    EpisodeRecord,
    episode_frames,
    refuse_foreign,
)


@dataclass(frozen=True)
class CollectConfig:
    """What ``d2a collect`` does.

    Attributes:
        tasks: task names or env ids; each gets ``episodes`` successful demonstrations.
        out: data set directory.
        episodes: successful episodes to keep per task (the paper: 10).
        seed: seed of the first attempt; attempt k uses seed + k.
        max_attempts_factor: give up on a task after ``episodes * max_attempts_factor`` attempts
            (None: 3, or :data:`DART_MAX_ATTEMPTS_FACTOR` with ``dart_noise``; see ``attempts_factor``).
        max_episode_steps: steps per episode (DP3/MP1: 200).
        env_kwargs: point-cloud settings passed to ``gym.make`` (cameras, num_points, ...).
        append: add to an existing data set (resuming an interrupted collection).
        overwrite: replace an existing data set.
        progress: show a progress bar.
        action_noise: std of Gaussian noise added to the expert's actions (0: demonstrations);
            with ``keep_failures`` the rollouts off the demonstrated states that a world model
            can learn from beside the demonstrations.
        keep_failures: store every attempt (``episodes`` then counts attempts), not only successes.
        expert: the Adroit expert, ``"controller"`` or ``"planner"`` (None: the task's default,
            :func:`collectors.adroit_experts.default_expert_kind`); Meta-World has one.
        dart_noise: std of Gaussian noise on the executed actions while the stored labels stay
            the expert's (DART): demonstrations that also show how the expert recovers.
        student: a policy that acts while the expert labels (DAgger); every attempt is kept
            (``episodes`` counts attempts) and, labelled, trains policies like demonstrations.
        student_labels: False stores the student's own actions instead, unlabelled: rollouts of
            the policy (``d2a collect --policy``), for a world model or to measure what it imagines
            on the states the policy reaches (``d2a bench change``).
        ray_address: run the attempts on Ray (``"local"``, ``"auto"`` or a cluster address);
            ``None``: in this process.
    """

    tasks: tuple[str, ...]
    out: str
    episodes: int = 10
    seed: int = 0
    max_attempts_factor: int | None = None
    max_episode_steps: int = d2a_envs.DEFAULT_MAX_EPISODE_STEPS
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    append: bool = False
    overwrite: bool = False
    progress: bool = True
    ray_address: str | None = None
    action_noise: float = 0.0
    keep_failures: bool = False
    expert: str | None = None
    dart_noise: float = 0.0
    student: Student | None = None
    student_labels: bool = True

    @property
    def expert_settings(self) -> ExpertSettings:
        return ExpertSettings(self.expert, self.action_noise, self.dart_noise, self.student, self.student_labels)

    @property
    def keeps_every_attempt(self) -> bool:
        return self.keep_failures or self.student is not None

    @property
    def attempts_factor(self) -> int:
        """``max_attempts_factor``, or where it is not given the default for this collection."""
        if self.max_attempts_factor is not None:
            return self.max_attempts_factor
        return DART_MAX_ATTEMPTS_FACTOR if self.dart_noise else PLAIN_MAX_ATTEMPTS_FACTOR


# Attempts per kept episode allowed by default. The DART-perturbed expert fails more often
# (Door at noise 0.05: 10 kept of 23 attempts; Hammer at 0.1: 10 of 46).
PLAIN_MAX_ATTEMPTS_FACTOR = 3
DART_MAX_ATTEMPTS_FACTOR = 10


def demonstrations_tag(dart_noise: float, expert: str | None = None) -> str:
    """The suffix that names data, world models and runs apart by their demonstrations: made with
    DART noise (``_dart<std>``), or by a chosen Adroit expert (``_<kind>``)."""
    return (f"_dart{dart_noise:g}" if dart_noise else "") + (f"_{expert}" if expert else "")


def _open_output(config: CollectConfig) -> DemoDataset:
    out = Path(config.out)
    if config.append and config.overwrite:
        raise ValueError("choose one of --append and --overwrite")
    capacity = len(config.tasks) * config.episodes * config.max_episode_steps
    if config.append:
        if not out.exists() or holds_only_lock(out):
            return DemoDataset.create(out, capacity)
        return DemoDataset.open(out)
    return DemoDataset.create(out, capacity, overwrite=config.overwrite)


def _collection_for(dataset: DemoDataset, task: str, config: CollectConfig) -> CollectionRecord:
    """The record this run continues: the same task and seed resumes, anything else is new."""
    expert = expert_name(task, config.expert)
    student = None if config.student is None else config.student.name
    env_kwargs = json.loads(json.dumps(_env_kwargs(config)))  # as stored: tuples become lists
    known = dataset.metadata.tasks.setdefault(task, env_kwargs)
    if known != env_kwargs:
        raise DatasetError(
            f"{dataset.directory} holds {task} collected with env kwargs {known}, not {env_kwargs}: "
            f"collect into another directory"
        )
    for record in dataset.metadata.collections:
        if record.task != task:
            continue
        if record.seed == config.seed:
            settings = (record.action_noise, record.keep_failures, record.expert or expert, record.dart_noise,
                        record.student, record.student_labels)
            if settings != (config.action_noise, config.keep_failures, expert, config.dart_noise, student,
                            config.student_labels):
                raise DatasetError(
                    f"{dataset.directory}: the {task} collection of seed {config.seed} used action noise "
                    f"{record.action_noise}, keep_failures={record.keep_failures}, the {record.expert} expert, "
                    f"DART noise {record.dart_noise} and student {record.student} (labelled: "
                    f"{record.student_labels}); resume it with those, or pass another --seed")
            return record
        # The attempts this run may make must not reuse a seed: that would store an episode twice.
        last = config.seed + config.episodes * config.attempts_factor - 1
        if record.attempts and config.seed <= record.seed + record.attempts - 1 and record.seed <= last:
            raise DatasetError(
                f"seeds {config.seed}..{last} (this run's attempts) overlap seeds {record.seed}.."
                f"{record.seed + record.attempts - 1}, already used for {task}; pass --seed {record.seed} to resume "
                f"that collection or a seed from {record.seed + record.attempts} on"
            )
    record = CollectionRecord(task=task, seed=config.seed, action_noise=config.action_noise,
                              keep_failures=config.keep_failures, expert=expert, dart_noise=config.dart_noise,
                              student=student, student_labels=config.student_labels)
    dataset.metadata.collections.append(record)
    return record


def _env_kwargs(config: CollectConfig) -> dict[str, Any]:
    return {**config.env_kwargs, "max_episode_steps": config.max_episode_steps}


def collect_task(dataset: DemoDataset, task: str, config: CollectConfig) -> CollectionRecord:
    """Run the expert of ``task`` until ``config.episodes`` successes are stored."""
    spec = d2a_envs.get_task(task)
    record = _collection_for(dataset, spec.name, config)
    collection_index = dataset.metadata.collections.index(record)
    max_attempts = config.episodes * config.attempts_factor
    if record.kept >= config.episodes:
        return record
    # What the expert and the student read beyond the data set's observations (not stored).
    env_kwargs = {**_env_kwargs(config), **expert_env_kwargs(spec.name),
                  **(config.student.env_kwargs if config.student is not None else {})}
    first_seed = record.seed + record.attempts
    if config.ray_address is None:
        rollouts = _expert_episodes(spec.name, env_kwargs, first_seed, config.max_episode_steps,
                                    config.expert_settings)
    else:
        rollouts = _expert_episodes_on_ray(spec.name, env_kwargs, first_seed, config.max_episode_steps,
                                           config.ray_address, config.expert_settings)
    unit = "episodes" if config.keeps_every_attempt else "demos"
    bar = tqdm(total=config.episodes, initial=record.kept, desc=f"{spec.name} {unit}", disable=not config.progress)
    try:
        for rollout in rollouts:
            episode_seed = int(rollout["episode_seed"][0])
            record.attempts = episode_seed - record.seed + 1
            success = bool(rollout["next", "success"].any())
            if success or config.keeps_every_attempt:
                index = len(dataset.metadata.episodes)
                record.kept += 1  # before add_episode: its metadata write commits the episode and the count together
                dataset.add_episode(
                    episode_frames(rollout, index),
                    EpisodeRecord(
                        index=index, task=spec.name, start=0, length=0, success=success,
                        episode_return=float(rollout["next", "reward"].sum()), collection=collection_index,
                        attempt=episode_seed - record.seed, min_points_in_crop=int(rollout["num_points_in_crop"].min()),
                    ),
                )
                bar.update(1)
            dataset.commit()
            bar.set_postfix(tried=record.attempts)
            if record.kept >= config.episodes or record.attempts >= max_attempts:
                break
    finally:
        bar.close()
        rollouts.close()  # stops the collector, or cancels the Ray jobs in flight
    if record.kept < config.episodes:
        message = f"{spec.name}: only {record.kept} successful episodes in {record.attempts} attempts"
        warnings.warn(message, stacklevel=2)
    return record


def _expert_episodes(task: str, env_kwargs: dict[str, Any], first_seed: int, max_steps: int,
                     expert: ExpertSettings) -> Iterator[TensorDictBase]:
    """The expert's episodes with seeds ``first_seed``, ``first_seed + 1``, ... (one rollout each)."""
    env = make_torchrl_env(task, env_kwargs, seed=first_seed)
    if expert.student is not None:
        env.append_transform(InitTracker())  # a student policy clears its state where an episode starts
    collector = Collector(
        env, make_expert(task, expert), frames_per_batch=max_steps, trajs_per_batch=1, traj_format="cat",
        total_frames=-1,
        auto_register_policy_transforms=False,  # the expert keeps its own state: leave the env as it is
    )
    try:
        yield from collector
    finally:
        collector.shutdown()


def _expert_episode(task: str, env_kwargs: dict[str, Any], seed: int, max_steps: int,
                    expert: ExpertSettings) -> TensorDictBase:
    """One Ray job: the expert's episode of ``seed`` (module-level: Ray imports it)."""
    episodes = _expert_episodes(task, env_kwargs, seed, max_steps, expert)
    try:
        return next(episodes)
    finally:
        episodes.close()


def _expert_episodes_on_ray(task: str, env_kwargs: dict[str, Any], first_seed: int, max_steps: int,
                            address: str, expert: ExpertSettings) -> Iterator[TensorDictBase]:
    """:func:`_expert_episodes` with every episode a Ray job, yielded in seed order."""
    jobs = ((task, env_kwargs, seed, max_steps, expert) for seed in itertools.count(first_seed))
    arrived: dict[int, TensorDictBase] = {}
    following = 0
    with contextlib.closing(as_completed(_expert_episode, jobs, address)) as outcomes:  # closing cancels the rest
        for index, outcome in outcomes:
            if isinstance(outcome, Lost):
                raise JobsLost(f"{task}: the Ray worker of attempt seed {first_seed + index} died on every "
                                   f"attempt ({outcome.reason}); the episodes before it are stored, rerun with "
                                   "--append")
            arrived[index] = outcome
            while following in arrived:
                yield arrived.pop(following)
                following += 1


def collect(config: CollectConfig) -> DemoDataset:
    """Collect every task of ``config`` into ``config.out``; returns the data set."""
    if config.episodes <= 0:
        raise ValueError(f"episodes must be positive, got {config.episodes}")
    specs = [d2a_envs.get_task(task) for task in config.tasks]  # unknown names fail before any work
    for spec in specs:
        make_expert(spec.name, config.expert_settings)  # a task without that expert, or bad noise, fails here
        if expert_name(spec.name, config.expert_settings.kind) == "planner" and \
                config.env_kwargs.get("action_repeat", 1) != 1:
            raise ValueError(f"the {spec.name} planner plans one action per simulator step; with action_repeat "
                             f"{config.env_kwargs['action_repeat']} its plans would run at the wrong pace (the "
                             "controllers and the scripted experts act on the state and hold any pace)")
    if config.max_episode_steps < 1 or config.attempts_factor < 1:
        raise ValueError("max_episode_steps and max_attempts_factor must be at least 1")
    # Bad env settings (num_points 0, an unknown camera...) fail here, before the output
    # directory is touched: --overwrite must not wipe a data set for a run that cannot start.
    gym.make(specs[0].env_id, **_env_kwargs(config)).close()
    refuse_foreign(Path(config.out))  # before the lock file is created in it
    with ray_connection(config.ray_address), exclusive_writer(config.out):  # one Ray connection for every task
        dataset = _open_output(config)
        for spec in specs:
            record = collect_task(dataset, spec.name, config)
            kept = "episodes" if config.keeps_every_attempt else "successful episodes"
            noise = (f", action noise {config.action_noise}" if config.action_noise else
                     f", DART noise {config.dart_noise} on the executed actions" if config.dart_noise else
                     "" if config.student is None else
                     f", {config.student.name} acting, the expert labelling" if config.student_labels else
                     f", {config.student.name} acting, its own actions stored")
            print(f"{spec.name}: kept {record.kept} {kept} of {record.attempts} tried (seed {record.seed}{noise})")
    return dataset
