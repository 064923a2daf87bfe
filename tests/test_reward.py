"""Reward from imagined clouds: Chamfer distance against brute force, progress semantics."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from metaworld.policies import ENV_POLICY_MAP

from d2a_agents.reward import GoalChamferReward, chamfer_distance


def brute_force_chamfer(a: np.ndarray, b: np.ndarray) -> float:
    a_to_b = np.mean([min(np.linalg.norm(p - q) for q in b) for p in a])
    b_to_a = np.mean([min(np.linalg.norm(q - p) for p in a) for q in b])
    return a_to_b + b_to_a


def test_chamfer_against_brute_force():
    rng = np.random.default_rng(0)
    a, b = rng.random((37, 3)), rng.random((23, 3))
    assert chamfer_distance(a, b) == pytest.approx(brute_force_chamfer(a, b), rel=1e-5)
    assert chamfer_distance(a, b, chunk=5) == pytest.approx(chamfer_distance(b, a), rel=1e-5)
    assert chamfer_distance(a, a) == 0.0
    # A single point moved by 0.1 m from a single point: 0.1 each way.
    assert chamfer_distance(np.zeros((1, 3)), np.array([[0.1, 0, 0]])) == pytest.approx(0.2)
    with pytest.raises(ValueError, match="non-empty"):
        chamfer_distance(np.zeros((0, 3)), a)


def test_progress_sign_follows_the_motion():
    rng = np.random.default_rng(1)
    cloud = rng.random((200, 3)) * 0.1
    goal = cloud + np.array([0.5, 0.0, 0.0])
    reward = GoalChamferReward(goal)
    towards, away = cloud + [0.2, 0, 0], cloud - [0.2, 0, 0]
    assert reward(cloud, towards) > 0 > reward(cloud, away)
    assert reward(cloud, cloud) == 0.0
    assert reward.potential(goal) == 0.0


def test_potential_rises_along_a_successful_demonstration():
    import d2a_envs  # noqa: F401

    env = gym.make("D2A-MetaWorld-Reach-v0", image_size=64, num_points=256)
    expert = ENV_POLICY_MAP["reach-v3"]()
    observation, _ = env.reset(seed=0)
    clouds = [observation["point_cloud"]]
    for _ in range(60):
        observation, *_ = env.step(expert.get_action(observation["state"]))
        clouds.append(observation["point_cloud"])
    reward = GoalChamferReward(clouds[-1])
    assert reward.potential(clouds[0]) < reward.potential(clouds[30]) < reward.potential(clouds[-1])
    assert reward(clouds[0], clouds[30]) > 0
