"""Adroit controllers: inverse kinematics and the servo map against MuJoCo's own computations,
actions that depend on the state alone, and a seeded door opened within the episode."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
import torch
from gymnasium_robotics.utils.rotations import euler2quat

from collectors.adroit_controllers import ControllerReplica, HandKinematics
from collectors.adroit_experts import AdroitExpert, default_expert_kind
from collectors.envs import make_torchrl_env
from collectors.pen_sequences import DEFAULT_LIBRARY, SequenceLibrary
from d2a_envs.suites.adroit import AdroitEnv, physics_vector
from tests.conftest import SMALL_ENV_KWARGS

ARM = ("ARTz", "ARRx", "ARRy")


@pytest.fixture(scope="module")
def door():
    env = AdroitEnv("door", physics_obs=True)
    env.reset(seed=0)
    yield env
    env.close()


def test_inverse_kinematics_reaches_a_point_the_arm_can_reach(door):
    """The goal is where forward kinematics puts the palm for other arm joint values; from the
    start pose, the solution brings the palm there (MuJoCo's kinematics at the solution)."""
    model = door.model
    kinematics = HandKinematics(model, *door.action_map)
    probe = mujoco.MjData(model)
    probe.qpos[:] = door.data.qpos
    chosen = {"ARTz": 0.2, "ARRx": -0.2, "ARRy": 0.15}
    for joint, value in chosen.items():
        probe.qpos[model.joint(joint).qposadr[0]] = value
    mujoco.mj_kinematics(model, probe)
    goal = probe.site("S_grasp").xpos.copy()
    solution = kinematics.solve(door.data, "S_grasp", goal, ARM)
    for joint, value in zip(ARM, solution, strict=True):
        probe.qpos[model.joint(joint).qposadr[0]] = value
    mujoco.mj_kinematics(model, probe)
    assert np.linalg.norm(probe.site("S_grasp").xpos - goal) < 1e-3
    assert np.linalg.norm(goal - door.data.site("S_grasp").xpos) > 0.1  # a real move, not the start


def test_the_action_map_makes_the_servos_cancel_the_bias_forces(door):
    """At the action for "hold where you are", MuJoCo's actuator forces equal the bias forces
    (gravity, Coriolis) on every actuated joint whose control is not clipped."""
    model, data = door.model, mujoco.MjData(door.model)
    data.qpos[:] = door.data.qpos
    data.qpos[model.joint("ARRx").qposadr[0]] = -0.3  # a pose where gravity pulls on the arm
    mujoco.mj_forward(model, data)
    kinematics = HandKinematics(model, *door.action_map)
    action = kinematics.action(data, kinematics.hold(data))
    mean, scale = door.action_map
    data.ctrl[:] = mean + action * scale
    mujoco.mj_forward(model, data)
    dofs = model.jnt_dofadr[model.actuator_trnid[:, 0]]
    free = np.abs(action) < 1.0
    assert free[:4].all() and free.sum() > 10  # the arm and some fingers (the rest sit at a range end)
    np.testing.assert_allclose(data.actuator_force[free], data.qfrc_bias[dofs][free], atol=1e-6)
    assert np.abs(data.qfrc_bias[dofs]).max() > 1.0  # the check is not trivially 0 = 0


def test_the_controller_acts_on_the_state_alone():
    """Two replicas given the same physics vector act the same; another state, another action."""
    env = AdroitEnv("door", state_obs=False, physics_obs=True)
    observation, _ = env.reset(seed=3)
    first, second = ControllerReplica("door"), ControllerReplica("door")
    action = first.act(observation["physics"])
    assert np.array_equal(action, second.act(observation["physics"]))
    moved, *_ = env.step(action)
    assert not np.array_equal(first.act(moved["physics"]), action)
    env.close()


def test_the_default_experts_and_refusals():
    assert default_expert_kind("door") == default_expert_kind("hammer") == "controller"
    assert default_expert_kind("pen") == "planner"  # until policies learn from its library
    assert AdroitExpert("adroit-pen", kind="controller").kind == "controller"
    assert AdroitExpert("adroit-door").kind == "controller"
    assert AdroitExpert("adroit-door", kind="planner").kind == "planner"
    with pytest.raises(ValueError, match="no controller for"):
        ControllerReplica("relocate")
    with pytest.raises(ValueError, match="unknown expert kind"):
        AdroitExpert("adroit-door", kind="oracle")


def test_the_pen_controller_plays_the_library_at_the_target_and_the_step_of_the_state():
    """Its action: the shipped library's nearest node for the target the env shows, at the step the
    state's clock gives (5 physics steps of 2 ms per control step)."""
    env = AdroitEnv("pen", state_obs=False, physics_obs=True)
    env.reset(seed=0)
    env.model.body_quat[env.model.body("target").id] = euler2quat(np.array([0.3, -0.5, 0.0]))
    replica, library = ControllerReplica("pen"), SequenceLibrary.load(DEFAULT_LIBRARY)
    for step in range(4):
        physics = physics_vector(env.model, env.data, "pen")
        np.testing.assert_allclose(replica.act(physics), np.clip(library.action(0.3, -0.5, step), -1, 1), atol=1e-9)
        env.step(np.zeros(env.action_space.shape, dtype=np.float32))
    env.close()


@pytest.mark.parametrize("task", ["adroit-door", "adroit-hammer", "adroit-pen"])
def test_the_controller_solves_a_seeded_layout_within_the_episode(task):
    env = make_torchrl_env(task, {**SMALL_ENV_KWARGS, "physics_obs": True}, seed=7)
    with torch.no_grad():
        rollout = env.rollout(200, AdroitExpert(task), break_when_any_done=False)
    env.close()
    assert bool(rollout["next", "success"].any())


def test_collect_records_the_expert_and_refuses_to_resume_with_another(tmp_path):
    from collectors.collect import CollectConfig, collect
    from collectors.storage import DatasetError, DemoDataset

    config = CollectConfig(tasks=("adroit-door",), out=str(tmp_path / "door"), episodes=1, max_attempts_factor=1,
                           seed=7, env_kwargs=SMALL_ENV_KWARGS, progress=False)
    dataset = DemoDataset.open(collect(config).directory)
    assert dataset.metadata.collections[0].expert == "controller" and dataset.metadata.episodes[0].success
    with pytest.raises(DatasetError, match="the controller expert"):
        collect(dataclasses.replace(config, episodes=2, append=True, expert="planner"))
    with pytest.raises(ValueError, match="applies to Adroit tasks"):
        collect(dataclasses.replace(config, tasks=("reach",), out=str(tmp_path / "reach"), expert="planner"))
