"""Adroit hand tasks (gymnasium-robotics ``AdroitHand*-v1``) in the suite-environment shape."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from d2a_envs.suites.base import SuiteEnv

ADROIT_ENV_IDS = {"hammer": "AdroitHandHammer-v1", "door": "AdroitHandDoor-v1", "pen": "AdroitHandPen-v1"}


# What each task's reset changes in the model (not in the state): the door's frame, the
# nail board, the pen's target orientation. A replica of the scene needs them to plan.
_LAYOUT_FIELDS = {"hammer": ("body_pos", "nail_board"), "door": ("body_pos", "frame"), "pen": ("body_quat", "target")}
PHYSICS_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS


class AdroitEnv(SuiteEnv):
    """One Adroit task: ``hammer``, ``door`` or ``pen``.

    Observation: ``agent_pos`` = positions of the actuated hand (and arm) joints, ``state``
    = the task's own observation vector; with ``physics_obs``, ``physics`` = MuJoCo's full
    physics state followed by the layout the reset drew (see :func:`set_physics`), all a
    planner needs to replay the scene in a copy of the model. Seeding is Gymnasium's.
    """

    def __init__(self, task: str, state_obs: bool = True, physics_obs: bool = False) -> None:
        if task not in ADROIT_ENV_IDS:
            raise ValueError(f"unknown Adroit task {task!r}; choose one of {sorted(ADROIT_ENV_IDS)}")
        import gymnasium_robotics  # imported on use: it prints a notice about its dense rewards

        gym.register_envs(gymnasium_robotics)
        self.task = task
        # The raw env: episode length is set by the D2A registration, not gymnasium-robotics.
        sim = gym.make(ADROIT_ENV_IDS[task], max_episode_steps=None).unwrapped
        self._actuated_qpos = _actuated_joint_qpos_addresses(sim.model)
        super().__init__(
            sim,
            agent_pos_dim=len(self._actuated_qpos),
            state_dim=sim.observation_space.shape[0],
            action_space=sim.action_space,
            state_obs=state_obs,
        )
        self.physics_obs = physics_obs
        if physics_obs:
            size = physics_size(sim.model, task)
            self.observation_space.spaces["physics"] = gym.spaces.Box(-np.inf, np.inf, (size,), np.float64)

    def agent_pos(self) -> np.ndarray:
        return self._sim.data.qpos[self._actuated_qpos].copy()

    @property
    def model_path(self) -> str:
        """The MJCF file of the scene (a planner compiles its own copy from it)."""
        return str(self._sim.fullpath)

    @property
    def frame_skip(self) -> int:
        """Physics steps per control step."""
        return int(self._sim.frame_skip)

    @property
    def action_map(self) -> tuple[np.ndarray, np.ndarray]:
        """(mean, scale): the actuator controls of an action ``a`` are ``mean + a * scale``."""
        return np.asarray(self._sim.act_mean), np.asarray(self._sim.act_rng)

    def _observation(self, state: np.ndarray) -> dict[str, np.ndarray]:
        observation = super()._observation(state)
        if self.physics_obs:
            observation["physics"] = physics_vector(self._sim.model, self._sim.data, self.task)
        return observation

    def _reset_simulator(self, seed: int | None) -> tuple[np.ndarray, dict[str, Any]]:
        state, info = self._sim.reset(seed=seed)
        return state, dict(info)


def _actuated_joint_qpos_addresses(model: mujoco.MjModel) -> np.ndarray:
    """qpos addresses of the joints driven by an actuator, in actuator order."""
    joint_ids = [
        model.actuator_trnid[i, 0]
        for i in range(model.nu)
        if model.actuator_trntype[i] == mujoco.mjtTrn.mjTRN_JOINT
    ]
    return np.array([model.jnt_qposadr[j] for j in joint_ids], dtype=np.int64)


def _layout(model: mujoco.MjModel, task: str) -> np.ndarray:
    field, body = _LAYOUT_FIELDS[task]
    return getattr(model, field)[model.body(body).id]


def physics_size(model: mujoco.MjModel, task: str) -> int:
    """Length of the ``physics`` observation of ``task``."""
    return mujoco.mj_stateSize(model, PHYSICS_STATE) + _layout(model, task).size


def physics_vector(model: mujoco.MjModel, data: mujoco.MjData, task: str) -> np.ndarray:
    """MuJoCo's full physics state of ``data``, then the layout fields of ``task``'s model."""
    state = np.empty(mujoco.mj_stateSize(model, PHYSICS_STATE))
    mujoco.mj_getState(model, data, state, PHYSICS_STATE)
    return np.concatenate([state, _layout(model, task)])


def set_physics(model: mujoco.MjModel, data: mujoco.MjData, task: str, physics: np.ndarray) -> None:
    """Put a ``physics`` observation into a replica: its layout into ``model``, its state into
    ``data`` (positions derived by a kinematics pass)."""
    size = mujoco.mj_stateSize(model, PHYSICS_STATE)
    if physics.shape != (physics_size(model, task),):
        raise ValueError(f"a {task} physics vector has {physics_size(model, task)} values, got {physics.shape}")
    _layout(model, task)[:] = physics[size:]
    mujoco.mj_setState(model, data, np.asarray(physics[:size], dtype=np.float64), PHYSICS_STATE)
    mujoco.mj_kinematics(model, data)
