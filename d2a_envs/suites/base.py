"""Common shape of the simulator environments that the point-cloud wrapper builds on.

A suite environment wraps one benchmark task and returns a ``Dict`` observation with
``agent_pos`` (proprioception) and, unless disabled, ``state`` (the simulator's own flat
observation, what scripted experts read). It exposes ``model`` and ``data`` so that
sensors can look at the scene, and puts ``success`` in ``info`` at every step.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces


class SuiteEnv(gym.Env, ABC):
    """Base class: shared observation space, action checks and info handling.

    Subclasses wrap a MuJoCo-based benchmark env ``sim`` (exposing ``model`` and ``data``).
    """

    metadata = {"render_modes": []}

    def __init__(
        self, sim: gym.Env, agent_pos_dim: int, state_dim: int, action_space: spaces.Box, state_obs: bool
    ) -> None:
        self._sim = sim
        self.state_obs = state_obs
        self.action_space = action_space
        observation = {"agent_pos": spaces.Box(-np.inf, np.inf, (agent_pos_dim,), np.float32)}
        if state_obs:
            observation["state"] = spaces.Box(-np.inf, np.inf, (state_dim,), np.float64)
        self.observation_space = spaces.Dict(observation)

    @property
    def model(self) -> mujoco.MjModel:
        """The MuJoCo model of the scene."""
        return self._sim.model

    @property
    def data(self) -> mujoco.MjData:
        """The MuJoCo data (current state) of the scene."""
        return self._sim.data

    def close(self) -> None:
        self._sim.close()

    @abstractmethod
    def agent_pos(self) -> np.ndarray:
        """Proprioception of the robot in the current state."""

    @abstractmethod
    def _reset_simulator(self, seed: int | None) -> tuple[np.ndarray, dict[str, Any]]:
        """Reset the task, seeding its layout when ``seed`` is given; returns (state, info)."""

    def _step_simulator(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict[str, Any]]:
        """Advance one control step; returns (state, reward, terminated, info with success)."""
        state, reward, terminated, _, info = self._sim.step(action)
        return state, float(reward), bool(terminated), dict(info)

    def _observation(self, state: np.ndarray) -> dict[str, np.ndarray]:
        observation = {"agent_pos": self.agent_pos().astype(np.float32)}
        if self.state_obs:
            observation["state"] = np.asarray(state, dtype=np.float64)
        return observation

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        state, info = self._reset_simulator(seed)
        info["success"] = False
        return self._observation(state), info

    def step(self, action: np.ndarray):
        action = np.asarray(action, dtype=np.float32)
        if action.shape != self.action_space.shape:
            raise ValueError(f"action must have shape {self.action_space.shape}, got {action.shape}")
        if not np.all(np.isfinite(action)):
            raise ValueError(f"action contains NaN or inf: {action}")
        state, reward, terminated, info = self._step_simulator(action)
        info["success"] = bool(info.get("success", False))
        return self._observation(state), float(reward), bool(terminated), False, info
