"""Experts as TorchRL policies: Meta-World's scripted ones, Adroit's controllers and planners."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from metaworld.policies import ENV_POLICY_MAP
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential

import d2a_envs
from collectors.adroit_experts import AdroitExpert, default_expert_kind
from collectors.envs import STATE_KEY


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


class ActionNoise(TensorDictModuleBase):
    """Adds Gaussian noise of standard deviation ``std`` to ``action`` (clipped to [-1, 1]).

    The noise of a step depends only on its episode's seed and step count, so a noisy
    collection is reproducible and resumes exactly, on any worker.
    """

    def __init__(self, std: float) -> None:
        super().__init__()
        if not std >= 0:
            raise ValueError(f"action noise must be a standard deviation >= 0, not {std}")
        self.std = std
        self.in_keys, self.out_keys = ["action", "episode_seed", "step_count"], ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get("action")
        seed = int(tensordict.get("episode_seed").reshape(-1)[0])
        step = int(tensordict.get("step_count").reshape(-1)[0])
        noise = np.random.default_rng([seed, step]).normal(0.0, self.std, size=tuple(action.shape))
        tensordict.set("action", (action + torch.as_tensor(noise, dtype=action.dtype)).clamp(-1.0, 1.0))
        return tensordict


def expert_name(task: str, kind: str | None = None) -> str:
    """Which expert acts on ``task``: ``scripted`` (Meta-World), or the Adroit ``kind``
    (``controller`` or ``planner``; None: the task's default)."""
    spec = d2a_envs.get_task(task)
    if spec.suite != "adroit":
        if kind is not None:
            raise ValueError(f"the expert kind ({kind}) applies to Adroit tasks; {spec.env_id} has one scripted expert")
        return "scripted"
    return kind or default_expert_kind(spec.task)


def make_expert(task: str, action_noise: float = 0.0, kind: str | None = None) -> TensorDictModuleBase:
    """The expert of ``task``: Meta-World's scripted policy, or the Adroit controller or planner
    (``kind``; None: the task's default); with ``action_noise``, its actions perturbed by
    :class:`ActionNoise` (what it then executes)."""
    spec = d2a_envs.get_task(task)
    name = expert_name(task, kind)
    expert = ScriptedExpert(spec.name) if name == "scripted" else AdroitExpert(spec.name, name)
    return TensorDictSequential(expert, ActionNoise(action_noise)) if action_noise else expert


def expert_env_kwargs(task: str) -> dict[str, Any]:
    """What the env of ``task`` must add for its expert (the Adroit planners read ``physics``)."""
    return {"physics_obs": True} if d2a_envs.get_task(task).suite == "adroit" else {}
