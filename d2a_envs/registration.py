"""Register every task of the task table as a Gymnasium id."""

from __future__ import annotations

import gymnasium as gym

from d2a_envs.defaults import DEFAULT_MAX_EPISODE_STEPS
from d2a_envs.tasks import TASKS


def register_all() -> None:
    """Register ``D2A-MetaWorld-<Task>-v0`` and ``D2A-Adroit-<Task>-v0`` (idempotent)."""
    for spec in TASKS:
        if spec.env_id in gym.registry:
            continue
        gym.register(
            id=spec.env_id,
            entry_point="d2a_envs.factory:make_env",
            kwargs={"suite": spec.suite, "task": spec.task},
            max_episode_steps=DEFAULT_MAX_EPISODE_STEPS,
        )
