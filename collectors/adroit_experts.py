"""Adroit experts: a controller or predictive sampling on a copy of the scene.

Nothing can be downloaded here (DP3 and MP1 use pretrained VRL3 agents). The expert reads
the env's ``physics`` observation (full MuJoCo state and the reset's layout) and copies it
into its own copy of the scene; there it either runs the task's controller
(:mod:`collectors.adroit_controllers`: a deterministic function of the state, the default
for Door and Hammer) or plans the next action by model-predictive control on the true
simulator (:mod:`collectors.predictive_sampling`). The planners' costs are this module's
own: gymnasium-robotics' dense rewards add +0.1 x the palm's distance to the handle or
hammer, which pays for staying away.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

import d2a_envs
from collectors.adroit_controllers import ControllerReplica
from collectors.predictive_sampling import PredictiveSampler, SamplingConfig, TaskCost, Trajectories, planning_model
from d2a_envs.suites.adroit import AdroitEnv, set_physics

PHYSICS_KEY = "physics"
EXPERT_KINDS = ("controller", "planner")


def _distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(a - b, axis=-1)


def _effort(t: Trajectories) -> np.ndarray:
    return 0.01 * (t.actions**2).mean(axis=(1, 2))


def _door_cost(model: mujoco.MjModel) -> TaskCost:
    hinge, latch = model.joint("door_hinge").qposadr[0], model.joint("latch").qposadr[0]

    def score(t: Trajectories) -> np.ndarray:
        reach = _distance(t.sites[:, :, 0], t.sites[:, :, 1]).mean(1)  # palm to handle
        unlatched = np.clip(1.2 - t.qpos[:, :, latch], 0.0, None).mean(1)  # turn the handle
        opened = (1.57 - t.qpos[:, :, hinge]).mean(1)  # swing the door
        return reach + 0.5 * unlatched + 2.0 * opened + _effort(t)

    return TaskCost(sites=("S_grasp", "S_handle"), bodies=(), score=score)


def _hammer_cost(model: mujoco.MjModel) -> TaskCost:
    def score(t: Trajectories) -> np.ndarray:
        palm, head, nail, goal = (t.sites[:, :, i] for i in range(4))
        grasp = _distance(palm, t.bodies[:, :, 0]).mean(1)  # palm to the hammer
        strike = _distance(head, nail).mean(1)  # hammer head to the nail
        drive = _distance(nail, goal).mean(1)  # nail into the board
        return grasp + strike + 10.0 * drive + _effort(t)

    return TaskCost(sites=("S_grasp", "tool", "S_target", "nail_goal"), bodies=("Object",), score=score)


def _pen_cost(model: mujoco.MjModel) -> TaskCost:
    def unit(v: np.ndarray) -> np.ndarray:
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    def score(t: Trajectories) -> np.ndarray:
        top, bottom, target_top, target_bottom, ball = (t.sites[:, :, i] for i in range(5))
        centre = t.bodies[:, :, 0]
        angle = np.arccos(np.clip((unit(top - bottom) * unit(target_top - target_bottom)).sum(-1), -1.0, 1.0))
        away = np.clip(_distance(centre, ball) - 0.04, 0.0, None)  # free within 4 cm of the goal
        dropped = centre[..., 2] < 0.075  # the env's own "dropped" height
        return (100.0 * away + angle + 5.0 * dropped).mean(1) + _effort(t)

    return TaskCost(sites=("object_top", "object_bottom", "target_top", "target_bottom", "eps_ball"),
                    bodies=("Object",), score=score)


# Per task: the cost and the sampling settings (measured in docs/environments.md). The first
# knot is held (Door) or barely moved (Hammer, Pen), so the executed actions are smooth enough
# to imitate. Pen plans on a 10 ms model (one physics step per control step instead of five of
# 2 ms: 4-5x cheaper rollouts) with 2 x 128 samples, the wrist sampled wider than the fingers.
EXPERTS = {
    "door": (_door_cost, SamplingConfig(horizon=16, knots=4, samples=32, sigma=0.5, first_knot_noise=0.0)),
    "hammer": (_hammer_cost, SamplingConfig(horizon=16, knots=4, samples=48, sigma=0.3, first_knot_noise=0.3)),
    "pen": (_pen_cost, SamplingConfig(horizon=30, knots=4, samples=128, iterations=2, sigma=0.15,
                                      sigma_by_actuator=(("A_WRJ", 0.6),), cost_every=1, hold_start=True,
                                      planning_timestep=0.01, first_knot_noise=0.3)),
}


class PlannerReplica:
    """The planning model of one task (cost sensors added) and its planner, seeded per episode."""

    def __init__(self, task: str) -> None:
        scene = AdroitEnv(task, state_obs=False)
        make_cost, config = EXPERTS[task]
        cost = make_cost(scene.model)
        self.task = task
        self.model = planning_model(mujoco.MjSpec.from_file(scene.model_path), cost, config.planning_timestep)
        self.data = mujoco.MjData(self.model)
        physics_steps = max(1, round(scene.frame_skip * scene.model.opt.timestep / self.model.opt.timestep))
        self.planner = PredictiveSampler(self.model, physics_steps, *scene.action_map, cost, config)
        scene.close()

    def act(self, physics: np.ndarray, step: int, seed: int) -> np.ndarray:
        set_physics(self.model, self.data, self.task, physics)
        if step == 0:
            self.planner.reset(self.data, seed=seed)
        return self.planner.plan(self.data)[0]


class _ControllerReplica(ControllerReplica):
    """A controller replica that takes (and ignores) the step and seed a planner needs."""

    def act(self, physics: np.ndarray, step: int = 0, seed: int = 0) -> np.ndarray:
        return super().act(physics)


class AdroitExpert(TensorDictModuleBase):
    """The expert of one Adroit task, as a TorchRL policy: its controller (``kind="controller"``,
    the default where the task has one) or its planner (``kind="planner"``).

    Reads ``physics`` (make the env with ``physics_obs=True``), ``step_count`` and
    ``episode_seed`` (:func:`collectors.envs.make_torchrl_env` provides both) and writes
    ``action``. A controller acts on the state alone; a planner is re-seeded from each
    episode's seed, so a seed gives the same demonstration. Works on unbatched and batched
    tensordicts (a replica of the scene per env).

    Example:
        >>> env = make_torchrl_env("adroit-door", {"physics_obs": True}, seed=0)
        >>> rollout = env.rollout(200, AdroitExpert("adroit-door"))
        >>> bool(rollout["next", "success"].any())
        True
    """

    def __init__(self, task: str, kind: str | None = None) -> None:
        super().__init__()
        spec = d2a_envs.get_task(task)
        if spec.suite != "adroit":
            raise ValueError(f"Adroit experts exist for Adroit tasks only, not {spec.env_id}")
        kind = kind or default_expert_kind(spec.task)
        if kind not in EXPERT_KINDS:
            raise ValueError(f"unknown expert kind {kind!r}; choose one of {EXPERT_KINDS}")
        self.task, self.kind = spec.task, kind
        self.in_keys = [PHYSICS_KEY, "step_count", "episode_seed"]
        self.out_keys = ["action"]
        self._replicas: list[PlannerReplica | _ControllerReplica] = []

    def _replica(self, index: int) -> PlannerReplica | _ControllerReplica:
        """The replica of the scene of the ``index``-th env of a batch."""
        make = _ControllerReplica if self.kind == "controller" else PlannerReplica
        while len(self._replicas) <= index:
            self._replicas.append(make(self.task))
        return self._replicas[index]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if PHYSICS_KEY not in tensordict.keys():
            raise KeyError(f"the {self.task} expert acts on {PHYSICS_KEY!r}: make the env with physics_obs=True "
                           f"(collectors.experts.expert_env_kwargs)")
        physics = tensordict.get(PHYSICS_KEY)
        batch = physics.shape[:-1]
        flat = physics.reshape(-1, physics.shape[-1]).detach().cpu().numpy().astype(np.float64)
        steps = tensordict.get("step_count").reshape(-1).tolist()
        seeds = tensordict.get("episode_seed").reshape(-1).tolist()
        actions = []
        for index, (vector, step, seed) in enumerate(zip(flat, steps, seeds, strict=True)):
            actions.append(self._replica(index).act(vector, int(step), int(seed)))
        action = torch.as_tensor(np.stack(actions), dtype=torch.float32).reshape(*batch, -1)
        tensordict.set(self.out_keys[0], action.to(physics.device))
        return tensordict


# Pen keeps its planner by default until policies are shown to learn from its sequence library
# (docs/environments.md, "Adroit controllers").
DEFAULT_EXPERTS = {"door": "controller", "hammer": "controller", "pen": "planner"}


def default_expert_kind(task: str) -> str:
    """The expert ``d2a collect`` uses for an Adroit task (door, hammer, pen) unless told."""
    return DEFAULT_EXPERTS[task]
