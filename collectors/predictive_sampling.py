"""Predictive sampling: model-predictive control by random search on the true simulator.

At every control step the planner perturbs a nominal action sequence (a few knots, linearly
interpolated over the horizon), rolls every candidate out from the current state with
``mujoco.rollout`` (in C), scores the trajectories with a task cost and keeps the best as the
next nominal, shifted by one step (Howell et al., 2022, "Predictive Sampling: Real-time
Behaviour Synthesis with MuJoCo"). The nominal itself is always a candidate. Seeded, it is
deterministic.

The planning model is the scene's own model compiled with one frame-position sensor per
site and body the cost reads (:func:`planning_model`), so the rollouts return those positions
directly; it may take a coarser timestep than the scene (fewer physics steps per control
step, a cheaper and slightly less exact prediction).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np
from mujoco import rollout

_SENSOR_PREFIX = "planning/"


@dataclass(frozen=True)
class SamplingConfig:
    """Settings of :class:`PredictiveSampler`.

    Attributes:
        horizon: control steps per rollout.
        knots: knots of the action sequence over the horizon (linear in between).
        samples: candidates per iteration, the nominal included.
        iterations: sampling rounds per control step, each around the best so far.
        sigma: standard deviation of the knot noise, in normalised action units ([-1, 1]).
        sigma_by_actuator: (actuator name prefix, sigma) pairs that override ``sigma``.
        cost_every: the cost reads every ``cost_every``-th control step of a rollout.
        hold_start: start each episode from the action that holds the current joint
            positions (position servos) instead of the middle of the action range.
        planning_timestep: timestep of the planning model in seconds (None: the scene's).
        first_knot_noise: the first knot's noise as a fraction of the others'. Below 1 the
            executed actions change only as fast as the plan bends towards its later knots
            (0: the previous plan's next action): demonstrations a policy can imitate,
            instead of a new random draw at every step.
    """

    horizon: int = 16
    knots: int = 4
    samples: int = 32
    iterations: int = 1
    sigma: float = 0.3
    sigma_by_actuator: tuple[tuple[str, float], ...] = ()
    cost_every: int = 2
    hold_start: bool = False
    planning_timestep: float | None = None
    first_knot_noise: float = 1.0

    def __post_init__(self) -> None:
        if self.knots < 2 or self.horizon < self.knots or self.samples < 2 or self.cost_every < 1:
            raise ValueError(f"need knots >= 2, horizon >= knots, samples >= 2, cost_every >= 1: {self}")
        if self.iterations < 1 or not self.sigma > 0 or not all(s > 0 for _, s in self.sigma_by_actuator):
            raise ValueError(f"iterations must be >= 1 and every sigma positive: {self}")
        if not 0.0 <= self.first_knot_noise <= 1.0:
            raise ValueError(f"first_knot_noise must be in [0, 1], got {self.first_knot_noise}")


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


def planning_model(spec: mujoco.MjSpec, cost: TaskCost, timestep: float | None = None) -> mujoco.MjModel:
    """The scene of ``spec`` with a frame-position sensor for each of the cost's sites and
    bodies (the rollouts then return their positions), at ``timestep`` if given. The sensors
    change nothing else: bodies, joints and dynamics are the scene's."""
    for kind, names in ((mujoco.mjtObj.mjOBJ_SITE, cost.sites), (mujoco.mjtObj.mjOBJ_BODY, cost.bodies)):
        for name in names:
            spec.add_sensor(name=f"{_SENSOR_PREFIX}{name}", type=mujoco.mjtSensor.mjSENS_FRAMEPOS, objtype=kind,
                            objname=name)
    model = spec.compile()
    if timestep is not None:
        model.opt.timestep = timestep
    return model


class PredictiveSampler:
    """Plans normalised actions for a scene whose actuators take ``mean + a * scale``.

    Args:
        model: the planning model (:func:`planning_model`; its layout must match the scene's).
        physics_steps: physics steps of ``model`` per control step.
        action_mean, action_scale: the env's map from [-1, 1] to actuator controls.
        cost: the task cost.
        config: sampling settings.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        physics_steps: int,
        action_mean: np.ndarray,
        action_scale: np.ndarray,
        cost: TaskCost,
        config: SamplingConfig = SamplingConfig(),
    ) -> None:
        self.model, self.physics_steps, self.cost, self.config = model, physics_steps, cost, config
        self.action_mean, self.action_scale = np.asarray(action_mean), np.asarray(action_scale)
        self._rollout_data = [mujoco.MjData(model)]
        self._site_columns = self._sensor_columns(cost.sites)
        self._body_columns = self._sensor_columns(cost.bodies)
        names = [model.actuator(i).name for i in range(model.nu)]
        self.sigma = np.array([next((s for prefix, s in config.sigma_by_actuator if name.startswith(prefix)),
                                    config.sigma) for name in names])
        self._knot_times = np.linspace(0.0, config.horizon - 1, config.knots)
        steps = np.arange(config.horizon)
        left = np.clip(np.searchsorted(self._knot_times, steps, side="right") - 1, 0, config.knots - 2)
        gap = self._knot_times[left + 1] - self._knot_times[left]
        self._left, self._weight = left, ((steps - self._knot_times[left]) / gap)[None, :, None]
        read = np.arange(config.cost_every - 1, config.horizon, config.cost_every)
        self._read_steps = (read + 1) * physics_steps - 1  # the physics step that ends each read control step
        self.nominal = np.zeros((config.knots, model.nu))
        self._rng = np.random.default_rng(0)

    def _sensor_columns(self, names: Sequence[str]) -> np.ndarray:
        """Columns of the rollouts' sensordata holding the xyz of each named frame."""
        try:
            addresses = [self.model.sensor(f"{_SENSOR_PREFIX}{name}").adr[0] for name in names]
        except KeyError as error:
            raise ValueError(f"the planning model lacks the cost's sensors ({error}): build it with planning_model") \
                from error
        return np.array([[a, a + 1, a + 2] for a in addresses], dtype=np.int64).reshape(-1, 3)

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
        best_knots, best_actions, best_cost = self.nominal, None, np.inf
        for _ in range(config.iterations):
            noise = self._rng.normal(0.0, 1.0, (config.samples, config.knots, model.nu)) * self.sigma
            noise[0] = 0.0  # the best so far stays a candidate
            noise[:, 0] *= config.first_knot_noise
            candidates = np.clip(best_knots[None] + noise, -1.0, 1.0)
            actions = self.actions(candidates)
            controls = np.repeat(self.action_mean + actions * self.action_scale, self.physics_steps, axis=1)
            # One physics step more: a step's sensors describe the state it started from, so the
            # positions of the state after step k are the sensors of step k + 1.
            controls = np.concatenate([controls, controls[:, -1:]], axis=1)
            states, sensors = rollout.rollout(model, self._rollout_data, state, controls)
            costs = self.cost.score(self._trajectories(states, sensors, actions))
            best = int(np.argmin(costs))
            best_knots, best_actions, best_cost = candidates[best], actions[best], float(costs[best])
        self.nominal = self._shifted(best_actions)
        return best_actions[0].copy(), best_cost

    def _trajectories(self, states: np.ndarray, sensors: np.ndarray, actions: np.ndarray) -> Trajectories:
        read = self._read_steps
        qpos = states[:, read, 1 : 1 + self.model.nq]  # column 0 of a state is the time
        frames = sensors[:, read + 1]  # the positions of those same states
        return Trajectories(qpos=qpos, sites=frames[..., self._site_columns], bodies=frames[..., self._body_columns],
                            actions=actions)

    def _shifted(self, actions: np.ndarray) -> np.ndarray:
        """Knots of ``actions`` (horizon, nu) one control step later (the last step held)."""
        times = np.minimum(self._knot_times + 1.0, self.config.horizon - 1)
        steps = np.arange(self.config.horizon)
        return np.stack([np.interp(times, steps, actions[:, j]) for j in range(actions.shape[1])], axis=1)
