"""TorchRL integration: registered ids under GymEnv, and PointCloudTransform on plain MuJoCo envs."""

from __future__ import annotations

from functools import partial

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.wrappers import TimeLimit
from torchrl.envs import GymEnv, GymWrapper, ParallelEnv, TransformedEnv, check_env_specs

from collectors.envs import make_torchrl_env
from d2a_envs import SUITE_DEFAULTS, PointCloudConfig, PointCloudSensor  # registers the D2A-* ids
from d2a_envs.suites.metaworld import MetaWorldEnv
from d2a_envs.torchrl_transforms import PointCloudTransform, mujoco_model_data

NUM_POINTS = 256
CONFIG = SUITE_DEFAULTS["metaworld"].updated(num_points=NUM_POINTS)


def suite_env(config: PointCloudConfig = CONFIG, seed: int = 0) -> TransformedEnv:
    """D2A's Meta-World suite env (no point-cloud wrapper) under TorchRL, plus the transform."""
    base = GymWrapper(TimeLimit(MetaWorldEnv("hammer-v3"), 200))
    return TransformedEnv(base, PointCloudTransform(config, seed=seed))


def assert_in_crop_box(clouds: torch.Tensor, config: PointCloudConfig) -> None:
    points = clouds.reshape(-1, clouds.shape[-1]).numpy()
    assert config.crop_box.contains(points).all()


@pytest.mark.parametrize(
    ("env_id", "kwargs"),
    [
        ("D2A-MetaWorld-Hammer-v0", {"num_points": NUM_POINTS}),
        ("D2A-Adroit-Door-v0", {"num_points": 128, "image_size": 64}),
    ],
)
def test_registered_ids_pass_check_env_specs(env_id: str, kwargs: dict) -> None:
    env = GymEnv(env_id, **kwargs)
    assert env.observation_spec["point_cloud"].shape == (kwargs["num_points"], 3)
    check_env_specs(env, seed=0)
    env.close()


def test_parallel_env_runs_d2a_envs_in_worker_processes() -> None:
    # TorchRL's way to run copies of an env in processes: each worker builds its own env
    env = ParallelEnv(2, partial(make_torchrl_env, "reach", {"num_points": 32, "image_size": 32}))
    check_env_specs(env, seed=0)
    rollout = env.rollout(3)
    assert rollout["next", "point_cloud"].shape == (2, 3, 32, 3)
    assert rollout["next", "success"].dtype == torch.bool
    seeds = rollout["next", "episode_seed"]
    assert (seeds == seeds[:, :1]).all() and seeds[0, 0] != seeds[1, 0]  # one seed per worker's episode
    env.close()


@pytest.mark.parametrize("with_rgb", [False, True])
def test_transformed_env_passes_check_env_specs(with_rgb: bool) -> None:
    config = CONFIG.updated(with_rgb=with_rgb)
    env = suite_env(config)
    spec = env.observation_spec["point_cloud"]
    assert spec.shape == (NUM_POINTS, config.point_dim) and spec.dtype == torch.float32
    check_env_specs(env, seed=0)
    env.close()


def test_rollout_clouds_have_the_right_shape_and_lie_in_the_crop_box() -> None:
    env = suite_env()
    rollout = env.rollout(5)
    for key in ("point_cloud", ("next", "point_cloud")):
        clouds = rollout[key]
        assert clouds.shape == (5, NUM_POINTS, 3) and clouds.dtype == torch.float32
        assert_in_crop_box(clouds, CONFIG)
    assert not torch.equal(rollout["point_cloud"][0], rollout["next", "point_cloud"][-1])  # the arm moved
    env.close()


def test_clouds_match_the_gymnasium_wrapper_and_the_sensor() -> None:
    env = suite_env()
    gym_env = gym.make("D2A-MetaWorld-Hammer-v0", num_points=NUM_POINTS)
    observation, info = gym_env.reset(seed=3)
    reset = env.reset(seed=3)
    model, data = mujoco_model_data(env.base_env)
    np.testing.assert_array_equal(data.qpos, gym_env.unwrapped.data.qpos)  # same simulator state
    assert info["num_points_in_crop"] >= NUM_POINTS  # FPS only, so no draw from either generator
    np.testing.assert_array_equal(reset["point_cloud"].numpy(), observation["point_cloud"])

    step = env.rand_step(reset)
    reading = PointCloudSensor(CONFIG).read(model, data, np.random.default_rng(0))
    assert reading.num_in_crop >= NUM_POINTS
    np.testing.assert_array_equal(step["next", "point_cloud"].numpy(), reading.points)
    env.close()
    gym_env.close()


def test_sparse_crop_is_filled_reproducibly_from_the_transform_seed() -> None:
    config = CONFIG.updated(num_points=4096, image_size=(32, 32))  # far more points than the crop holds
    clouds = [suite_env(config, seed=seed).reset(seed=0)["point_cloud"] for seed in (7, 7, 8)]
    assert torch.equal(clouds[0], clouds[1]) and not torch.equal(clouds[0], clouds[2])
    assert clouds[0].shape == (4096, 3)
    assert_in_crop_box(clouds[0], config)


def test_transform_works_on_a_plain_metaworld_env() -> None:
    # Meta-World's own MT1 env fails check_env_specs by itself (its cached observation
    # space bounds the goal to [0, 0] while the goal is observed), so only the cloud is checked.
    env = TransformedEnv(GymWrapper(gym.make("Meta-World/MT1", env_name="hammer-v3")), PointCloudTransform(CONFIG))
    rollout = env.rollout(3)
    clouds = rollout["next", "point_cloud"]
    assert clouds.shape == (3, NUM_POINTS, 3)
    assert env.observation_spec["point_cloud"].is_in(clouds[-1])
    assert_in_crop_box(clouds, CONFIG)
    env.close()


def test_env_without_mujoco_gives_a_clear_error() -> None:
    env = TransformedEnv(GymEnv("Pendulum-v1"), PointCloudTransform(CONFIG))
    with pytest.raises(TypeError, match="needs a MuJoCo simulator.*PendulumEnv"):
        env.reset()
