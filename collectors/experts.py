"""Experts as TorchRL policies: Meta-World's scripted ones, Adroit's controllers and planners."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from metaworld.policies import ENV_POLICY_MAP
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential

import d2a_envs
from collectors.adroit_experts import EXPERT_KINDS, AdroitExpert, default_expert_kind
from collectors.envs import STATE_KEY
from collectors.storage import EXPERT_ACTION_KEY


class ScriptedExpert(TensorDictModuleBase):
    """The hand-written ``metaworld.policies`` expert of one task, as a TorchRL policy.

    Reads the 39-d state (``observation`` under TorchRL) and writes ``action`` (4,), clipped
    to the action space [-1, 1]. Works on unbatched and batched tensordicts.

    Example:
        >>> env = make_torchrl_env("hammer")
        >>> rollout = env.rollout(200, ScriptedExpert("hammer"))
        >>> bool(rollout["next", "success"].any())
        True
    """

    def __init__(self, task: str, state_key: str = STATE_KEY) -> None:
        super().__init__()
        spec = d2a_envs.get_task(task)
        if spec.suite != "metaworld":
            raise ValueError(f"scripted experts exist for Meta-World tasks only, not {spec.env_id}")
        self.task = spec.task
        self.expert = ENV_POLICY_MAP[spec.task]()
        self.in_keys = [state_key]
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        states = tensordict.get(self.in_keys[0])
        flat = states.reshape(-1, states.shape[-1]).detach().cpu().numpy().astype(np.float64)
        actions = np.stack([np.clip(self.expert.get_action(state), -1.0, 1.0) for state in flat])
        action = torch.as_tensor(actions, dtype=torch.float32).reshape(*states.shape[:-1], actions.shape[-1])
        tensordict.set(self.out_keys[0], action.to(states.device))
        return tensordict


def step_noise(seed: int, step: int, std: float, shape: tuple[int, ...]) -> np.ndarray:
    """The Gaussian action noise of step ``step`` of the episode of seed ``seed``: a function of
    the two alone, so a noisy rollout is reproducible and resumes exactly, on any worker."""
    return np.random.default_rng([seed, step]).normal(0.0, std, size=shape)


class ExpertLabel(TensorDictModuleBase):
    """Keeps the expert's ``action`` under ``expert_action``, the label a data set stores, so
    that what comes after it in a sequence may change the executed ``action``: DART noise
    (:class:`ActionNoise`) or a student acting instead (:class:`Student`)."""

    in_keys = ["action"]
    out_keys = [EXPERT_ACTION_KEY]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(EXPERT_ACTION_KEY, tensordict.get("action").clone())
        return tensordict


class ActionNoise(TensorDictModuleBase):
    """Adds Gaussian noise of standard deviation ``std`` to ``action`` (clipped to [-1, 1]).

    The noise of a step depends only on its episode's seed and step count, so a noisy
    collection is reproducible and resumes exactly, on any worker. After an
    :class:`ExpertLabel`, the env executes the noisy action and the data set stores the
    expert's as the label (DART, Laskey et al., 2017: demonstrations that visit the states a
    policy drifts to, labelled with how the expert recovers).
    """

    def __init__(self, std: float) -> None:
        super().__init__()
        if not std >= 0:
            raise ValueError(f"action noise must be a standard deviation >= 0, not {std}")
        self.std = std
        self.in_keys = ["action", "episode_seed", "step_count"]
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        seed = int(tensordict.get("episode_seed").reshape(-1)[0])
        step = int(tensordict.get("step_count").reshape(-1)[0])
        noise = step_noise(seed, step, self.std, tuple(action.shape))
        tensordict.set("action", (action + torch.as_tensor(noise, dtype=action.dtype)).clamp(-1.0, 1.0))
        return tensordict


@dataclass(frozen=True)
class Student:
    """A policy that acts while the expert only labels (DAgger, Ross et al., 2011): the data set
    stores the expert's action in the states the student reaches, failures included.

    Attributes:
        name: what the data set records of the student (its checkpoint).
        make: a picklable factory of the acting TorchRL policy; it reads ``is_init``, which
            the collection env then provides.
        env_kwargs: what the env must add for the student to see its observations (not stored).
    """

    name: str
    make: Callable[[], TensorDictModuleBase]
    env_kwargs: dict[str, Any] = field(default_factory=dict)


def expert_name(task: str, kind: str | None = None) -> str:
    """Which expert acts on ``task``: ``scripted`` (Meta-World), or the Adroit ``kind``
    (``controller`` or ``planner``; None: the task's default)."""
    spec = d2a_envs.get_task(task)
    if spec.suite != "adroit":
        if kind is not None:
            raise ValueError(f"the expert kind ({kind}) applies to Adroit tasks; {spec.env_id} has one scripted expert")
        return "scripted"
    return kind or default_expert_kind(spec.task)


@dataclass(frozen=True)
class ExpertSettings:
    """Which expert acts and how its executed actions are perturbed.

    Attributes:
        kind: the Adroit expert, ``controller`` or ``planner`` (None: the task's default).
        action_noise: noise std on the executed and stored actions (rollouts for a world model).
        dart_noise: noise std on the executed actions only; the stored label stays the expert's.
        student: a policy whose actions are executed instead; the stored label stays the expert's.
        student_labels: with a student, False stores the student's own executed actions and the
            expert does not run: rollouts of the policy, not labelled states.
    """

    kind: str | None = None
    action_noise: float = 0.0
    dart_noise: float = 0.0
    student: Student | None = None
    student_labels: bool = True

    def __post_init__(self) -> None:
        if self.kind not in (None, *EXPERT_KINDS):
            raise ValueError(f"expert must be one of {EXPERT_KINDS} (or None: each task's default), not {self.kind!r}")
        if sum((bool(self.action_noise), bool(self.dart_noise), self.student is not None)) > 1:
            raise ValueError("choose one of action noise (rollouts), DART noise (demonstrations) and a student "
                             "(DAgger)")
        if not self.student_labels and self.student is None:
            raise ValueError("student_labels=False stores a student's own actions: give the student")


def make_expert(task: str, settings: ExpertSettings = ExpertSettings()) -> TensorDictModuleBase:
    """The expert of ``task``: Meta-World's scripted policy, or the Adroit controller or planner;
    with noise in ``settings``, its executed actions perturbed by :class:`ActionNoise`; with a
    student, the student's actions executed and the expert's kept as labels (or, without
    ``student_labels``, the student alone)."""
    if settings.student is not None and not settings.student_labels:
        return settings.student.make()
    spec = d2a_envs.get_task(task)
    name = expert_name(task, settings.kind)
    expert = ScriptedExpert(spec.name) if name == "scripted" else AdroitExpert(spec.name, name)
    if settings.student is not None:
        return TensorDictSequential(expert, ExpertLabel(), settings.student.make())
    if settings.dart_noise:
        return TensorDictSequential(expert, ExpertLabel(), ActionNoise(settings.dart_noise))
    if settings.action_noise:
        return TensorDictSequential(expert, ActionNoise(settings.action_noise))
    return expert


def expert_env_kwargs(task: str) -> dict[str, Any]:
    """What the env of ``task`` must add for its expert (the Adroit planners read ``physics``)."""
    return {"physics_obs": True} if d2a_envs.get_task(task).suite == "adroit" else {}
