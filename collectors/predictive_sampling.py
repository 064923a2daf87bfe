"""Predictive sampling: model-predictive control by random search on the true simulator.

At every control step the planner perturbs a nominal action sequence (a few knots, linearly
interpolated over the horizon), rolls every candidate out from the current state with
``mujoco.rollout`` (in C, on a replica of the scene), scores the trajectories with a task
cost and keeps the best as the next nominal, shifted by one step (Howell et al., 2022,
"Predictive Sampling: Real-time Behaviour Synthesis with MuJoCo"). The nominal itself is
always a candidate, so the plan's cost never rises from one step to the next without the
state changing. Seeded, it is deterministic.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import rollout


@dataclass(frozen=True)
class SamplingConfig:
    """Settings of :class:`PredictiveSampler`.

    Attributes:
        horizon: control steps per rollout.
        knots: knots of the action sequence over the horizon (linear in between).
        samples: candidates per step, the nominal included.
        sigma: standard deviation of the knot noise, in normalised action units ([-1, 1]).
        cost_every: the cost reads every ``cost_every``-th control step of a rollout.
        hold_start: start each episode from the action that holds the current joint
            positions (position servos) instead of the middle of the action range.
    """

    horizon: int = 16
    knots: int = 4
    samples: int = 32
    sigma: float = 0.3
    cost_every: int = 2
    hold_start: bool = False

    def __post_init__(self) -> None:
        if self.knots < 2 or self.horizon < self.knots or self.samples < 2 or self.cost_every < 1:
            raise ValueError(f"need knots >= 2, horizon >= knots, samples >= 2, cost_every >= 1: {self}")
        if not self.sigma > 0:
            raise ValueError(f"sigma must be positive, got {self.sigma}")


@dataclass(frozen=True)
class Trajectories:
    """What a cost sees of the rollouts, at the steps it reads (n candidates x T' steps).

    Attributes:
        qpos: joint positions (n, T', nq).
        sites: world positions of the cost's sites (n, T', n_sites, 3).
        bodies: world positions of the cost's bodies (n, T', n_bodies, 3).
        actions: the candidates' normalised actions over the whole horizon (n, T, nu).
    """

    qpos: np.ndarray
    sites: np.ndarray
    bodies: np.ndarray
    actions: np.ndarray


@dataclass(frozen=True)
class TaskCost:
    """A task cost: the sites and bodies it needs, and ``score(trajectories) -> (n,)``."""

    sites: Sequence[str]
    bodies: Sequence[str]
    score: Callable[[Trajectories], np.ndarray]


class PredictiveSampler:
    """Plans normalised actions for a MuJoCo scene whose actuators take ``mean + a * scale``.

    Args:
        model: the replica's model (its layout must match the real scene's).
        frame_skip: physics steps per control step.
        action_mean, action_scale: the env's map from [-1, 1] to actuator controls.
        cost: the task cost.
        config: sampling settings.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        frame_skip: int,
        action_mean: np.ndarray,
        action_scale: np.ndarray,
        cost: TaskCost,
        config: SamplingConfig = SamplingConfig(),
    ) -> None:
        self.model, self.frame_skip, self.cost, self.config = model, frame_skip, cost, config
        self.action_mean, self.action_scale = np.asarray(action_mean), np.asarray(action_scale)
        self._rollout_data = [mujoco.MjData(model)]
        self._kinematics = mujoco.MjData(model)
        self._sites = [model.site(name).id for name in cost.sites]
        self._bodies = [model.body(name).id for name in cost.bodies]
        self._knot_times = np.linspace(0.0, config.horizon - 1, config.knots)
        steps = np.arange(config.horizon)
        left = np.clip(np.searchsorted(self._knot_times, steps, side="right") - 1, 0, config.knots - 2)
        gap = self._knot_times[left + 1] - self._knot_times[left]
        self._left, self._weight = left, ((steps - self._knot_times[left]) / gap)[None, :, None]
        self._read_steps = np.arange(config.cost_every - 1, config.horizon, config.cost_every)
        self.nominal = np.zeros((config.knots, model.nu))
        self._rng = np.random.default_rng(0)

    def reset(self, data: mujoco.MjData, seed: int) -> None:
        """Start an episode from the scene in ``data``, with its own random stream."""
        self._rng = np.random.default_rng(seed)
        self.nominal[:] = 0.0
        if self.config.hold_start:
            joints = self.model.actuator_trnid[:, 0]
            held = (data.qpos[self.model.jnt_qposadr[joints]] - self.action_mean) / self.action_scale
            self.nominal[:] = np.clip(held, -1.0, 1.0)

    def actions(self, knots: np.ndarray) -> np.ndarray:
        """Per-step normalised actions (n, horizon, nu) of knot sequences (n, knots, nu)."""
        actions = knots[:, self._left] * (1.0 - self._weight) + knots[:, self._left + 1] * self._weight
        return np.clip(actions, -1.0, 1.0)

    def plan(self, data: mujoco.MjData) -> tuple[np.ndarray, float]:
        """The next normalised action from the scene in ``data`` and the chosen plan's cost."""
        config, model = self.config, self.model
        state = np.empty(mujoco.mj_stateSize(model, mujoco.mjtState.mjSTATE_FULLPHYSICS))
        mujoco.mj_getState(model, data, state, mujoco.mjtState.mjSTATE_FULLPHYSICS)
        noise = self._rng.normal(0.0, config.sigma, (config.samples, config.knots, model.nu))
        noise[0] = 0.0  # the nominal stays a candidate
        candidates = np.clip(self.nominal[None] + noise, -1.0, 1.0)
        actions = self.actions(candidates)
        controls = np.repeat(self.action_mean + actions * self.action_scale, self.frame_skip, axis=1)
        states, _ = rollout.rollout(model, self._rollout_data, state, controls)
        # the state at the end of each read control step; column 0 of a state is the time
        read = states[:, (self._read_steps + 1) * self.frame_skip - 1, 1 : 1 + model.nq]
        costs = self.cost.score(self._trajectories(read, actions))
        best = int(np.argmin(costs))
        self.nominal = self._shifted(actions[best])
        return actions[best, 0].copy(), float(costs[best])

    def _trajectories(self, qpos: np.ndarray, actions: np.ndarray) -> Trajectories:
        n, steps = qpos.shape[:2]
        sites = np.empty((n, steps, len(self._sites), 3))
        bodies = np.empty((n, steps, len(self._bodies), 3))
        kinematics = self._kinematics
        for i in range(n):
            for k in range(steps):
                kinematics.qpos[:] = qpos[i, k]
                mujoco.mj_kinematics(self.model, kinematics)
                sites[i, k] = kinematics.site_xpos[self._sites]
                bodies[i, k] = kinematics.xpos[self._bodies]
        return Trajectories(qpos=qpos, sites=sites, bodies=bodies, actions=actions)

    def _shifted(self, actions: np.ndarray) -> np.ndarray:
        """Knots of ``actions`` (horizon, nu) one control step later (the last step held)."""
        times = np.minimum(self._knot_times + 1.0, self.config.horizon - 1)
        steps = np.arange(self.config.horizon)
        return np.stack([np.interp(times, steps, actions[:, j]) for j in range(actions.shape[1])], axis=1)
