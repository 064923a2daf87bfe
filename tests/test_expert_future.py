"""The expert's true future cloud (``d2a-oracle``'s observation): the episode it looks ahead
from runs on untouched, and what it shows is what the scene shows H steps later."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from metaworld.policies import ENV_POLICY_MAP
from tensordict import TensorDict

from collectors.dataset import future_rows
from collectors.envs import EXPERT_FUTURE_KEY, make_torchrl_env
from collectors.expert_future import ExpertFuture
from d2a_envs.sampling import farthest_point_indices
from d2a_envs.wrappers import IMAGINED_KEY
from tests.conftest import SMALL_ENV_KWARGS

ENV_ID = "D2A-MetaWorld-Push-v0"


def expert_action(expert, observation: dict[str, np.ndarray]) -> np.ndarray:
    return np.clip(expert.get_action(observation["state"]), -1.0, 1.0)


def test_the_look_ahead_leaves_the_episode_untouched():
    plain = gym.make(ENV_ID, **SMALL_ENV_KWARGS)
    looking = ExpertFuture(gym.make(ENV_ID, **SMALL_ENV_KWARGS), horizon=4, num_points=32)
    expert = ENV_POLICY_MAP["push-v3"]()
    observed, _ = plain.reset(seed=3)
    looked, _ = looking.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(25):  # off the expert's path too: the look-ahead must not depend on it
        action = np.clip(expert_action(expert, observed) + rng.normal(0.0, 0.3, 4), -1.0, 1.0)
        observed, reward, _, _, info = plain.step(action)
        looked, looked_reward, _, _, looked_info = looking.step(action)
        for key in ("state", "agent_pos", "point_cloud"):
            np.testing.assert_array_equal(looked[key], observed[key])
        assert (looked_reward, looked_info["success"]) == (reward, info["success"])
        assert looked[IMAGINED_KEY].shape == (32, 3) and looking.observation_space[IMAGINED_KEY].shape == (32, 3)


def expert_episode(env: ExpertFuture, steps: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The look-ahead clouds and the clouds observed (FPS-sampled as the look-ahead samples) at
    every step of an episode the scripted expert drives (seed 7)."""
    expert = ENV_POLICY_MAP["push-v3"]()
    observation, _ = env.reset(seed=7)
    futures, clouds = [observation[IMAGINED_KEY]], [observation["point_cloud"]]
    for _ in range(steps):
        observation, *_ = env.step(expert_action(expert, observation))
        futures.append(observation[IMAGINED_KEY])
        clouds.append(observation["point_cloud"])
    return futures, [cloud[farthest_point_indices(cloud, env.num_points)] for cloud in clouds]


def test_the_future_is_the_cloud_the_expert_reaches_horizon_steps_later():
    horizon = 3
    futures, seen = expert_episode(ExpertFuture(gym.make(ENV_ID, **SMALL_ENV_KWARGS), horizon, num_points=32), 12)
    for t in range(len(seen) - horizon):
        np.testing.assert_array_equal(futures[t], seen[t + horizon])
    assert not np.array_equal(futures[0], seen[-1])  # the scene moves: equal clouds would prove nothing


def test_stacked_horizons_are_the_clouds_the_expert_reaches_at_each_horizon():
    env = ExpertFuture(gym.make(ENV_ID, **SMALL_ENV_KWARGS), horizon=4, num_points=32, stacked_horizons=(2, 1))
    assert env.observation_space[IMAGINED_KEY].shape == (3, 32, 3)
    futures, seen = expert_episode(env, 10)
    for t in range(len(seen) - 4):
        for k, horizon in enumerate((1, 2, 4)):  # nearest first
            np.testing.assert_array_equal(futures[t][k], seen[t + horizon])
    assert not np.array_equal(futures[0][0], futures[0][2])  # the horizons differ: equal clouds would prove nothing


def test_the_torchrl_env_takes_the_look_ahead_as_an_option():
    env = make_torchrl_env("push", {**SMALL_ENV_KWARGS, EXPERT_FUTURE_KEY: {"horizon": 2, "num_points": 16}}, seed=0)
    assert env.rollout(2)[IMAGINED_KEY].shape == (2, 16, 3)
    stacked = {"horizon": 2, "num_points": 16, "stacked_horizons": [1]}
    env = make_torchrl_env("push", {**SMALL_ENV_KWARGS, EXPERT_FUTURE_KEY: stacked}, seed=0)
    assert env.rollout(2)[IMAGINED_KEY].shape == (2, 2, 16, 3)


def test_only_a_meta_world_env_with_its_state_can_look_ahead():
    with pytest.raises(ValueError, match="Meta-World"):
        ExpertFuture(gym.make("D2A-Adroit-Door-v0", image_size=32, num_points=64), horizon=4, num_points=16)
    with pytest.raises(ValueError, match="'state'"):
        ExpertFuture(gym.make(ENV_ID, state_obs=False, **SMALL_ENV_KWARGS), horizon=4, num_points=16)


def test_future_rows_stay_inside_their_episode():
    frames = TensorDict({"episode": torch.tensor([5, 5, 5, 5, 2, 2, 9])}, batch_size=[7])
    assert future_rows(frames, 2).tolist() == [2, 3, 3, 3, 5, 5, 6]
    assert future_rows(frames, 0).tolist() == list(range(7))
