"""Adroit planning experts: the physics observation replays the scene, the planner's maths,
seeded determinism, and short seeded episodes that reach a stated sub-goal."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import torch

from collectors.adroit_experts import AdroitExpert
from collectors.envs import make_torchrl_env
from collectors.experts import expert_env_kwargs, make_expert
from collectors.predictive_sampling import PredictiveSampler, SamplingConfig, TaskCost, planning_model
from d2a_envs.suites.adroit import AdroitEnv, set_physics
from tests.conftest import SMALL_ENV_KWARGS

EXPERT_ENV = {**SMALL_ENV_KWARGS, "physics_obs": True}


@pytest.mark.parametrize("task", ["door", "hammer", "pen"])
def test_physics_observation_replays_the_scene_in_a_replica(task):
    """A replica given the physics vector steps exactly as the real scene does, layout included."""
    real, replica = AdroitEnv(task, physics_obs=True), AdroitEnv(task, state_obs=False)
    real.reset(seed=3)
    replica.reset(seed=99)  # another layout: the vector must carry the reset's draw
    rng = np.random.default_rng(0)
    for _ in range(3):
        observation, *_ = real.step(rng.uniform(-1, 1, real.action_space.shape).astype(np.float32))
    set_physics(replica.model, replica.data, task, observation["physics"])
    action = rng.uniform(-1, 1, real.action_space.shape).astype(np.float32)
    real.step(action)
    replica.step(action)
    np.testing.assert_allclose(replica.data.qpos, real.data.qpos, atol=1e-9)
    np.testing.assert_allclose(replica.data.site_xpos, real.data.site_xpos, atol=1e-9)
    with pytest.raises(ValueError, match="physics vector"):
        set_physics(replica.model, replica.data, task, observation["physics"][:-1])


def test_physics_observation_is_refused_outside_adroit():
    import gymnasium as gym

    import d2a_envs  # noqa: F401

    with pytest.raises(ValueError, match="physics_obs is available for Adroit"):
        gym.make("D2A-MetaWorld-Reach-v0", physics_obs=True, **SMALL_ENV_KWARGS)


def _slide_model(cost: TaskCost, timestep: float | None = None) -> mujoco.MjModel:
    """A point mass on a slide, driven by a position servo; a site marks it."""
    return planning_model(mujoco.MjSpec.from_string("""
    <mujoco><option timestep="0.01"/><worldbody><body name="mass">
      <joint name="x" type="slide" axis="1 0 0" damping="5"/><geom size="0.05" mass="1"/>
      <site name="tip" pos="0.1 0 0"/></body></worldbody>
      <actuator><position name="servo" joint="x" kp="50" ctrlrange="-1 1"/></actuator></mujoco>"""), cost, timestep)


def test_knots_interpolate_linearly_and_the_plan_shifts_by_one_step():
    cost = TaskCost(sites=("tip",), bodies=(), score=lambda t: np.zeros(len(t.actions)))
    config = SamplingConfig(horizon=7, knots=3)
    planner = PredictiveSampler(_slide_model(cost), 1, np.zeros(1), np.ones(1), cost, config)
    knots = np.array([[[0.0], [0.6], [-0.3]]])
    expected = np.interp(np.arange(7), [0, 3, 6], [0.0, 0.6, -0.3])  # knots at steps 0, 3, 6
    np.testing.assert_allclose(planner.actions(knots)[0, :, 0], expected, atol=1e-12)
    shifted = planner._shifted(planner.actions(knots)[0])
    np.testing.assert_allclose(shifted[:, 0], np.interp([1, 4, 6], np.arange(7), expected), atol=1e-12)


def test_the_planning_model_reports_the_cost_frames_and_keeps_the_dynamics():
    cost = TaskCost(sites=("tip",), bodies=("mass",), score=lambda t: np.zeros(len(t.actions)))
    model = _slide_model(cost, timestep=0.02)
    assert model.opt.timestep == 0.02 and model.nq == 1 and model.nu == 1
    data = mujoco.MjData(model)
    data.qpos[0] = 0.25
    mujoco.mj_forward(model, data)
    # the site sits 0.1 m along x from the body: sensors read 0.35 and 0.25
    np.testing.assert_allclose(data.sensordata, [0.35, 0, 0, 0.25, 0, 0], atol=1e-12)
    with pytest.raises(ValueError, match="planning_model"):
        PredictiveSampler(mujoco.MjModel.from_xml_string("<mujoco/>"), 1, np.zeros(0), np.ones(0), cost)


def test_the_cost_sees_positions_and_joints_of_the_same_states():
    """Sites handed to the cost sit 0.1 m from the joint position of the same read step."""
    seen = []

    def score(t):
        seen.append(t)
        return np.zeros(len(t.actions))

    cost = TaskCost(("tip",), ("mass",), score)
    model = _slide_model(cost)
    data = mujoco.MjData(model)
    planner = PredictiveSampler(model, 3, np.zeros(1), np.ones(1), cost, SamplingConfig(horizon=6, knots=2, samples=4))
    planner.reset(data, seed=0)
    planner.plan(data)
    t = seen[0]
    assert t.qpos.shape == (4, 3, 1) and t.sites.shape == (4, 3, 1, 3)  # every 2nd of 6 control steps
    assert np.ptp(t.qpos) > 1e-3  # the mass moves
    np.testing.assert_allclose(t.sites[..., 0, 0], t.qpos[..., 0] + 0.1, atol=1e-12)
    np.testing.assert_allclose(t.bodies[..., 0, 0], t.qpos[..., 0], atol=1e-12)


def test_a_held_first_knot_executes_the_previous_plans_next_action():
    def score(t):
        return np.abs(t.sites[:, :, 0, 0] - 0.5).mean(1)

    cost = TaskCost(("tip",), (), score)
    model = _slide_model(cost)
    data = mujoco.MjData(model)
    planner = PredictiveSampler(model, 2, np.zeros(1), np.ones(1), cost,
                                SamplingConfig(horizon=9, knots=3, samples=8, first_knot_noise=0.0))
    planner.reset(data, seed=0)
    for _ in range(5):
        planned_next = planner.nominal[0].copy()  # the last plan, one step on
        action, _ = planner.plan(data)
        np.testing.assert_allclose(action, planned_next, atol=1e-12)
        data.ctrl[:] = action
        mujoco.mj_step(model, data, 2)


def test_the_planner_drives_a_servo_to_a_target_it_only_sees_through_the_cost():
    target = 0.4

    def score(t):
        return np.abs(t.sites[:, :, 0, 0] - 0.1 - target).mean(1)

    cost = TaskCost(("tip",), (), score)
    model = _slide_model(cost)
    data = mujoco.MjData(model)
    planner = PredictiveSampler(model, 2, np.zeros(1), np.ones(1), cost,
                                SamplingConfig(horizon=10, knots=3, samples=16, sigma=0.3, iterations=2,
                                               sigma_by_actuator=(("serv", 0.5),)))
    assert planner.sigma.tolist() == [0.5]
    planner.reset(data, seed=0)
    costs = []
    for _ in range(60):
        action, plan_cost = planner.plan(data)
        costs.append(plan_cost)
        data.ctrl[:] = action
        mujoco.mj_step(model, data, 2)
    assert abs(data.qpos[0] - target) < 0.03, data.qpos[0]
    assert costs[-1] < 0.2 * costs[0]  # the plan cost falls as the mass settles


def _rollout(task: str, steps: int, seed: int = 0):
    """A planner's rollout (the planners are this file's subject; controllers have their own)."""
    env = make_torchrl_env(task, EXPERT_ENV, seed=seed)
    with torch.no_grad():
        rollout = env.rollout(steps, AdroitExpert(task, kind="planner"))
    env.close()
    return rollout


def test_a_seed_gives_the_same_demonstration():
    first, second = _rollout("adroit-door", 6), _rollout("adroit-door", 6)
    assert torch.equal(first["action"], second["action"])
    assert not torch.equal(first["action"], _rollout("adroit-door", 6, seed=1)["action"])


def test_door_expert_reaches_the_handle_and_turns_the_latch():
    """Seeded episode 0: the palm starts 34 cm from the handle; within 30 steps (0.3 s) it is
    within 8 cm and the latch (the handle's joint, 0 when closed) has turned past 0.5 rad."""
    rollout = _rollout("adroit-door", 30)
    scene = AdroitEnv("door", state_obs=False)
    distances, latches = [], []
    for physics in rollout["next", "physics"].numpy():
        set_physics(scene.model, scene.data, "door", physics)
        distances.append(np.linalg.norm(scene.data.site("S_grasp").xpos - scene.data.site("S_handle").xpos))
        latches.append(scene.data.joint("latch").qpos[0])
    assert min(distances) < 0.08, min(distances)
    assert max(latches) > 0.5, max(latches)


def test_hammer_expert_drives_the_nail_in_a_short_seeded_episode():
    rollout = _rollout("adroit-hammer", 45, seed=2)
    assert bool(rollout["next", "success"].any())


def test_an_env_without_the_physics_observation_gets_a_clear_error():
    env = make_torchrl_env("adroit-door", SMALL_ENV_KWARGS, seed=0)
    with pytest.raises(KeyError, match="physics_obs=True"):
        AdroitExpert("adroit-door")(env.reset())
    env.close()


def test_pen_expert_turns_the_pen_to_its_target_in_a_short_seeded_episode():
    """Seeded episode 1 (the target 39 degrees from the pen's start): success within 25 steps."""
    rollout = _rollout("adroit-pen", 25, seed=1)
    assert bool(rollout["next", "success"].any())


def test_experts_are_picked_per_suite_and_unknown_ones_refused():
    assert isinstance(make_expert("adroit-door"), AdroitExpert)
    assert type(make_expert("reach")).__name__ == "ScriptedExpert"
    assert expert_env_kwargs("adroit-hammer") == {"physics_obs": True} and expert_env_kwargs("reach") == {}
    with pytest.raises(ValueError, match="Adroit tasks only"):
        AdroitExpert("reach")
    with pytest.raises(ValueError, match="Meta-World tasks only"):
        from collectors.experts import ScriptedExpert

        ScriptedExpert("adroit-door")


def test_collect_stores_adroit_demonstrations_without_the_planner_input(tmp_path):
    from collectors.collect import CollectConfig, collect
    from collectors.storage import DemoDataset

    config = CollectConfig(tasks=("adroit-hammer",), out=str(tmp_path / "hammer"), episodes=1, max_attempts_factor=1,
                           seed=2, max_episode_steps=45, env_kwargs=SMALL_ENV_KWARGS, progress=False, expert="planner")
    dataset = DemoDataset.open(collect(config).directory)
    episode = dataset.episode(0)
    assert dataset.metadata.episodes[0].success and bool(episode["success"].any())
    assert episode["action"].shape == (45, 26) and episode["agent_pos"].shape == (45, 26)
    assert "physics" not in episode.keys() and "physics_obs" not in dataset.metadata.tasks["adroit-hammer"]
