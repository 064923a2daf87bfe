"""The true future as an observation: the cloud a perfect world model would imagine.

A world model trained on demonstrations learns to imagine the scene the expert would reach H
steps ahead. :class:`ExpertFuture` serves that future exactly: at every reset and step it
copies the simulator, lets the task's scripted expert act for H steps from the current state,
reads the point cloud there, and restores the copy, so the episode itself runs on untouched.
A policy that reads it (``d2a-oracle``, trained on the demonstrations' own clouds H steps
ahead) bounds what any imagined future can give that policy: the imagined cloud with no
model error. Stacked horizons serve several such clouds at once (H = 1, 2, 4: one look-ahead,
read at each). It needs the simulator, so it exists in evaluation only (Meta-World's scripted
experts; Adroit's need more than the state).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces
from metaworld.policies import ENV_POLICY_MAP

from d2a_envs.read_steps import ReadSteps, unread_observation
from d2a_envs.sampling import farthest_point_indices
from d2a_envs.suites.metaworld import MetaWorldEnv
from d2a_envs.wrappers import IMAGINED_KEY, PointCloudObservation, point_cloud_space

# Everything MuJoCo integrates from (positions, velocities, controls, mocap targets, warm start).
_STATE = mujoco.mjtState.mjSTATE_INTEGRATION


class ExpertFuture(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Add ``imagined_point_cloud``: the cloud after the scripted expert acts ``horizon`` steps
    from here, farthest-point sampled to ``num_points`` as the policies sample their clouds
    (``(num_points, 3)``); with ``stacked_horizons``, the clouds at every horizon, nearest first
    (``(K, num_points, 3)``).

    The simulator (MuJoCo's data and the Meta-World env's attributes) is restored after each
    look ahead, so observations, rewards and successes are those of the env without this wrapper
    (tested). The expert reads the 39-d ``state`` observation, so the env must keep it. With
    ``read_steps`` (:class:`~d2a_envs.read_steps.ReadSteps`), only the steps it reads look ahead;
    the others hold NaN.

    Example:
        >>> env = ExpertFuture(gym.make("D2A-MetaWorld-Push-v0"), horizon=4, num_points=64)
        >>> env.reset(seed=0)[0]["imagined_point_cloud"].shape
        (64, 3)
        >>> stacked = ExpertFuture(gym.make("D2A-MetaWorld-Push-v0"), 4, 64, stacked_horizons=(1, 2))
        >>> stacked.reset(seed=0)[0]["imagined_point_cloud"].shape
        (3, 64, 3)
    """

    def __init__(self, env: gym.Env, horizon: int, num_points: int, stacked_horizons: Sequence[int] = (),
                 read_steps: ReadSteps | None = None) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, horizon=horizon, num_points=num_points,
                                                 stacked_horizons=tuple(stacked_horizons), read_steps=read_steps)
        gym.Wrapper.__init__(self, env)
        base = env.unwrapped
        if not isinstance(base, MetaWorldEnv):
            raise ValueError(f"the expert's future needs a Meta-World scripted expert; {type(base).__name__} has none")
        if "state" not in env.observation_space.spaces:
            raise ValueError("the expert's future needs the env's 'state' observation (state_obs=True)")
        horizons = sorted({int(horizon), *map(int, stacked_horizons)})
        if horizons[0] < 1 or num_points < 1:
            raise ValueError(f"horizons and num_points must be at least 1, not {horizons} and {num_points}")
        self.horizons, self.num_points = tuple(horizons), int(num_points)
        self.stacked = bool(stacked_horizons)
        self.read_steps = ReadSteps.from_any(read_steps)
        self._step = 0
        self._clouds = _point_cloud_wrapper(env)
        self._expert = ENV_POLICY_MAP[base.task]()
        self._rng = np.random.default_rng(0)  # fills a cloud short of points; never the env's own generator
        future_space = point_cloud_space(dataclasses.replace(self._clouds.config, num_points=self.num_points))
        if self.stacked:
            shape = (len(self.horizons), *future_space.shape)
            low, high = (np.broadcast_to(bound, shape) for bound in (future_space.low, future_space.high))
            future_space = spaces.Box(low, high, shape, np.float32)
        self.observation_space = spaces.Dict({**env.observation_space.spaces, IMAGINED_KEY: future_space})

    def future_cloud(self, state: np.ndarray) -> np.ndarray:
        """The cloud ``horizon`` expert steps after the current simulator state (whose 39-d
        observation is ``state``), or the stacked clouds at every horizon; the simulator is left
        as it was."""
        sim = self.env.unwrapped._sim
        saved = np.empty(mujoco.mj_stateSize(sim.model, _STATE), dtype=np.float64)
        mujoco.mj_getState(sim.model, sim.data, saved, _STATE)
        attributes = dict(vars(sim))  # Meta-World's step counters and last observations are reassigned, not mutated
        clouds = []
        try:
            for step in range(1, self.horizons[-1] + 1):
                action = np.clip(self._expert.get_action(np.asarray(state, dtype=np.float64)), -1.0, 1.0)
                state = sim.step(action)[0]
                if step in self.horizons:
                    clouds.append(self._sampled(self._clouds.sensor.read(sim.model, sim.data, self._rng).points))
        finally:
            mujoco.mj_setState(sim.model, sim.data, saved, _STATE)
            mujoco.mj_forward(sim.model, sim.data)  # the positions derived from the state, as they were
            mujoco.mj_setState(sim.model, sim.data, saved, _STATE)  # and the warm start mj_forward moved
            vars(sim).clear()
            vars(sim).update(attributes)
        return np.stack(clouds) if self.stacked else clouds[0]

    def _sampled(self, points: np.ndarray) -> np.ndarray:
        if len(points) > self.num_points:
            points = points[farthest_point_indices(points, self.num_points)]
        return points.astype(np.float32)

    def _add_future(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        future = (self.future_cloud(observation["state"]) if self.read_steps(self._step)
                  else unread_observation(self.observation_space[IMAGINED_KEY]))
        return {**observation, IMAGINED_KEY: future}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        observation, info = self.env.reset(seed=seed, options=options)
        self._step = 0
        return self._add_future(observation), info

    def step(self, action: np.ndarray):
        observation, reward, terminated, truncated, info = self.env.step(action)
        self._step += 1
        return self._add_future(observation), reward, terminated, truncated, info


def _point_cloud_wrapper(env: gym.Env) -> PointCloudObservation:
    """The :class:`PointCloudObservation` inside ``env`` (its sensor reads the future scene)."""
    while isinstance(env, gym.Wrapper):
        if isinstance(env, PointCloudObservation):
            return env
        env = env.env
    raise ValueError("the expert's future is read by the env's point-cloud sensor: wrap a D2A env")
