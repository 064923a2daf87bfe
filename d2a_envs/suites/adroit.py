"""Adroit hand tasks (gymnasium-robotics ``AdroitHand*-v1``) in the suite-environment shape."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import mujoco
import numpy as np

from d2a_envs.suites.base import SuiteEnv

ADROIT_ENV_IDS = {"hammer": "AdroitHandHammer-v1", "door": "AdroitHandDoor-v1", "pen": "AdroitHandPen-v1"}


class AdroitEnv(SuiteEnv):
    """One Adroit task: ``hammer``, ``door`` or ``pen``.

    Observation: ``agent_pos`` = positions of the actuated hand (and arm) joints, ``state``
    = the task's own observation vector. Seeding is Gymnasium's.
    """

    def __init__(self, task: str, state_obs: bool = True) -> None:
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

    def agent_pos(self) -> np.ndarray:
        return self._sim.data.qpos[self._actuated_qpos].copy()

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
