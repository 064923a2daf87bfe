"""Meta-World v3 tasks with goal-observable state, seeded layouts and no internal time limit."""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np
from metaworld.env_dict import ALL_V3_ENVIRONMENTS

from d2a_envs.suites.base import SuiteEnv

# Meta-World raises if stepped past its own horizon; episode length is left to TimeLimit.
_UNLIMITED_PATH_LENGTH = 2**62

# The per-step measurements every Meta-World v3 task reports beside ``success``. Meta-World
# returns them only from ``step``, with types that vary by task (int, bool or float); here they
# are floats in every info, reset included (0.0 there), so vectorised envs see one schema.
METAWORLD_INFO_KEYS = (
    "near_object",
    "grasp_success",
    "grasp_reward",
    "in_place_reward",
    "obj_to_target",
    "unscaled_reward",
)


class MetaWorldEnv(SuiteEnv):
    """One Meta-World v3 task (e.g. ``hammer-v3``) with Gymnasium seeding semantics.

    Meta-World ignores ``reset(seed=...)`` and by default freezes the object layout. Here
    ``reset(seed=s)`` seeds the task's own generator, so the same ``s`` gives the same
    layout and different seeds give different layouts; the goal position is observable
    (the scripted experts need it).

    Observation: ``agent_pos`` = end-effector xyz and gripper opening (4,), ``state`` = the
    39-d Meta-World observation. ``info`` holds ``success`` and the floats named in
    :data:`METAWORLD_INFO_KEYS`, at reset as at every step.
    """

    def __init__(self, task: str, state_obs: bool = True) -> None:
        if task not in ALL_V3_ENVIRONMENTS:
            raise ValueError(f"unknown Meta-World task {task!r}")
        self.task = task
        sim = ALL_V3_ENVIRONMENTS[task]()
        sim._partially_observable = False
        sim.__dict__.pop("sawyer_observation_space", None)  # cached with the goal hidden
        sim._freeze_rand_vec = False
        sim.seeded_rand_vec = True
        sim._set_task_called = True
        sim.max_path_length = _UNLIMITED_PATH_LENGTH
        super().__init__(
            sim,
            agent_pos_dim=4,
            state_dim=sim.sawyer_observation_space.shape[0],
            action_space=sim.action_space,
            state_obs=state_obs,
        )

    def agent_pos(self) -> np.ndarray:
        return self._sim._get_curr_obs_combined_no_goal()[:4]

    def _reset_simulator(self, seed: int | None) -> tuple[np.ndarray, dict[str, Any]]:
        if seed is not None:
            self._sim.seed(seed)
        state, info = self._sim.reset()
        # Meta-World moves the goal site after its last forward pass: recompute the derived
        # positions so the first frame draws the marker where the goal is.
        mujoco.mj_kinematics(self._sim.model, self._sim.data)
        return state, {**info, **dict.fromkeys(METAWORLD_INFO_KEYS, 0.0)}

    def _step_simulator(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict[str, Any]]:
        state, reward, terminated, info = super()._step_simulator(action)
        return state, reward, terminated, {**info, **{key: float(info[key]) for key in METAWORLD_INFO_KEYS}}
