"""Imagined point clouds as observations: the Gymnasium wrapper, the TorchRL transform, ``world_model=``."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import GymWrapper, TransformedEnv, check_env_specs
from torchrl.envs.utils import step_mdp

from d2a_agents.checkpoint import CheckpointError, save_checkpoint
from d2a_agents.world_model.imagine import CHECKPOINT_KIND, Imaginer
from d2a_agents.world_model.observation import IMAGINED_KEY, ImaginationTransform, ImaginationWrapper, load_imaginer
from d2a_agents.world_model.triplane import TriplaneWorldModel, WorldModelConfig
from d2a_envs import SUITE_DEFAULTS, make_env  # registers the D2A-* ids

ENV_ID = "D2A-MetaWorld-Hammer-v0"
NUM_POINTS = 128
ENV_KWARGS = {"num_points": NUM_POINTS, "image_size": 48}
CROP_BOX = SUITE_DEFAULTS["metaworld"].crop_box
HISTORY = 3  # K
ACTIONS = np.array(  # K + 2 distinct actions, so the history must drop the oldest ones
    [[0.5, 0.0, 0.0, 1.0], [0.0, -0.5, 0.2, -1.0], [-0.3, 0.3, 0.0, 0.5], [0.1, 0.2, -0.6, 0.0], [0.9, -0.9, 0.4, 0.3]],
    dtype=np.float32,
)


def write_world_model(path: Path, box: tuple = (CROP_BOX.low, CROP_BOX.high), action_dim: int = 4,
                      kind: str = CHECKPOINT_KIND, tasks: tuple[str, ...] = ("hammer",)) -> Path:
    """A tiny untrained world model in the payload format of ``train_world_model``.

    The FiLM head is zero-initialised (actions have no effect before training), so it is
    randomised here: the tests must see the action history change the imagined cloud. The
    occupancy logits are pushed far below 0: no voxel passes the threshold and the imaginer
    keeps the most likely ones (as many as are occupied now); where that leaves fewer than N
    points it fills the cloud with repeats drawn from its generator, which the tests then
    must keep in step.
    """
    config = WorldModelConfig(resolution=(16, 16, 8), channels=8, horizon=2, action_history=HISTORY,
                              action_dim=action_dim, refine_dilations=(1, 2), decoder_hidden=32, decoder_layers=2)
    torch.manual_seed(0)
    model = TriplaneWorldModel(config)
    torch.nn.init.normal_(model.film[-1].weight, std=1.0)
    with torch.no_grad():
        model.decoder[-1].bias -= 10.0
    save_checkpoint(path, kind, {
        "config": config.to_dict(),
        "grid": {"box": {"low": tuple(box[0]), "high": tuple(box[1])}, "resolution": list(config.resolution)},
        "tasks": list(tasks), "env_kwargs": {task: ENV_KWARGS for task in tasks}, "num_points": NUM_POINTS,
        "model": model.state_dict(), "step": 0, "history": [],
    })
    return path


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_world_model(tmp_path_factory.mktemp("wm") / "wm.pt")


def assert_in_crop_box(cloud: np.ndarray) -> None:
    assert cloud.shape == (NUM_POINTS, 3) and cloud.dtype == np.float32
    assert CROP_BOX.contains(cloud).all()


def test_gym_make_with_world_model_gives_imagined_clouds_in_the_space(checkpoint: Path) -> None:
    env = gym.make(ENV_ID, world_model=str(checkpoint), **ENV_KWARGS)
    assert IMAGINED_KEY in env.observation_space.spaces
    observation, _ = env.reset(seed=0)
    assert env.observation_space.contains(observation)
    assert_in_crop_box(observation[IMAGINED_KEY])
    for action in ACTIONS[:3]:
        observation, *_ = env.step(action)
        assert env.observation_space.contains(observation)
        assert_in_crop_box(observation[IMAGINED_KEY])
    remade = gym.make(env.spec)  # the id, its kwargs and the wrapper stack round-trip
    assert IMAGINED_KEY in remade.reset(seed=0)[0]
    remade.close()
    env.close()


def test_the_imagined_cloud_can_be_smaller_than_the_env_cloud(checkpoint: Path) -> None:
    """A policy reading 16 points asks for 16 imagined points; the current cloud keeps its size."""
    env = gym.make(ENV_ID, world_model=str(checkpoint), imagined_points=16, **ENV_KWARGS)
    assert env.observation_space[IMAGINED_KEY].shape == (16, 3)
    observation, _ = env.reset(seed=0)
    assert observation[IMAGINED_KEY].shape == (16, 3) and observation["point_cloud"].shape[0] == NUM_POINTS
    assert env.observation_space.contains(observation)
    env.close()
    with pytest.raises(ValueError, match="need a world_model"):
        gym.make(ENV_ID, imagined_points=16, **ENV_KWARGS)
    with pytest.raises(ValueError, match="need a world_model"):
        gym.make(ENV_ID, imagined_output="change", **ENV_KWARGS)


def test_action_history_is_reset_and_holds_the_last_k_actions_in_order(checkpoint: Path) -> None:
    imaginer = Imaginer.from_checkpoint(checkpoint)  # an Imaginer works as well as a path
    env = ImaginationWrapper(make_env("metaworld", "hammer-v3", **ENV_KWARGS), imaginer, seed=0)
    assert env.history_length == HISTORY
    env.reset(seed=0)
    np.testing.assert_array_equal(env.action_history, np.zeros((HISTORY, 4), np.float32))
    for k in range(HISTORY + 1):
        env.step(ACTIONS[k])
        expected = np.concatenate([np.zeros((HISTORY, 4), np.float32), ACTIONS[: k + 1]])[-HISTORY:]
        np.testing.assert_array_equal(env.action_history, expected)  # oldest first
    np.testing.assert_array_equal(env.action_history, ACTIONS[1 : HISTORY + 1])
    env.reset()
    np.testing.assert_array_equal(env.action_history, np.zeros((HISTORY, 4), np.float32))
    assert imaginer.num_points == NUM_POINTS and env.imaginer is not imaginer  # the caller's object is untouched
    env.close()


@pytest.mark.parametrize(
    ("make_bad", "message"),
    [
        (lambda p: write_world_model(p, box=((-0.5, 0.25, 0.005), (0.6, 0.97, 0.7))), "crop box"),
        (lambda p: write_world_model(p, action_dim=6), "6-d actions"),
        (lambda p: write_world_model(p, kind="policy"), "not a world_model"),
        (lambda p: write_world_model(p, tasks=("push",)), r"trained on \['push'\], not on hammer"),
        (lambda p: torch.save({"model": {}}, p), "not a D2A checkpoint"),
        (lambda p: p.write_text("not a checkpoint"), "not a readable checkpoint"),
        (lambda p: None, "no checkpoint at"),
    ],
    ids=["other-crop-box", "other-action-size", "other-kind", "other-task", "foreign-dict", "text-file", "missing"],
)
def test_a_world_model_that_does_not_fit_is_refused(tmp_path: Path, make_bad, message: str) -> None:
    path = tmp_path / "bad.pt"
    make_bad(path)
    with pytest.raises(CheckpointError, match=message):
        gym.make(ENV_ID, world_model=str(path), **ENV_KWARGS)


def test_transform_refuses_a_world_model_of_another_crop_box(tmp_path: Path) -> None:
    path = write_world_model(tmp_path / "box.pt", box=((-0.5, 0.25, 0.005), (0.6, 0.97, 0.7)))
    env = TransformedEnv(GymWrapper(gym.make(ENV_ID, **ENV_KWARGS)))
    with pytest.raises(CheckpointError, match="crop box"):
        env.append_transform(ImaginationTransform(path))
        env.observation_spec  # noqa: B018  (specs may be built lazily)
    env.close()


def test_transform_passes_check_env_specs_and_rolls_out(checkpoint: Path) -> None:
    transform = ImaginationTransform(checkpoint)
    env = TransformedEnv(GymWrapper(gym.make(ENV_ID, **ENV_KWARGS)), transform)
    spec = env.observation_spec[IMAGINED_KEY]
    assert spec.shape == (NUM_POINTS, 3) and spec.dtype == torch.float32
    check_env_specs(env, seed=0)
    steps = HISTORY + 1
    rollout = env.rollout(steps)
    for key in (IMAGINED_KEY, ("next", IMAGINED_KEY)):
        clouds = rollout[key]
        assert clouds.shape == (steps, NUM_POINTS, 3) and clouds.dtype == torch.float32
        assert CROP_BOX.contains(clouds.reshape(-1, 3).numpy()).all()
    torch.testing.assert_close(transform.history, rollout["action"][-HISTORY:], rtol=0, atol=0)  # oldest first
    env.reset()
    assert not transform.history.any()
    env.close()


def test_wrapper_and_transform_imagine_what_the_imaginer_does(checkpoint: Path) -> None:
    seed = 3
    wrapped = gym.make(ENV_ID, world_model=str(checkpoint), **ENV_KWARGS)
    transform = ImaginationTransform(checkpoint, seed=seed)
    transformed = TransformedEnv(GymWrapper(gym.make(ENV_ID, **ENV_KWARGS)), transform)
    direct = Imaginer.from_checkpoint(checkpoint, num_points=NUM_POINTS, seed=seed)  # called in the same order

    def fresh(cloud: np.ndarray, history: np.ndarray) -> np.ndarray:
        return load_imaginer(direct, NUM_POINTS, seed=0)(cloud, history)

    observation, _ = wrapped.reset(seed=seed)
    td = transformed.reset(seed=seed)
    history = np.zeros((HISTORY, 4), np.float32)
    differs = False
    for step in range(len(ACTIONS) + 1):
        cloud = observation["point_cloud"]
        np.testing.assert_array_equal(td["point_cloud"].numpy(), cloud)  # same state
        expected = direct(cloud, history)
        np.testing.assert_array_equal(observation[IMAGINED_KEY], expected)
        np.testing.assert_array_equal(td[IMAGINED_KEY].numpy(), expected)
        assert len(np.unique(expected, axis=0)) < NUM_POINTS  # filled from the generator: seeding matters
        differs |= not np.array_equal(fresh(cloud, np.zeros_like(history)), fresh(cloud, history))
        if step == len(ACTIONS):
            break
        action = ACTIONS[step]
        observation, *_ = wrapped.step(action)
        td = step_mdp(transformed.step(td.set("action", torch.from_numpy(action))))
        history = np.concatenate([history[1:], action[None]])
    assert differs, "the action history never changed the imagined cloud: the test would not see a wrong history"
    wrapped.close()
    transformed.close()
