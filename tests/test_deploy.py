"""The deployment loop on a simulated robot and cameras behind the real interfaces: it fuses the
training cloud, imagines for a d2a policy, applies one action per period, logs its timing,
counts late steps and stops cleanly on Ctrl-C."""

from __future__ import annotations

import itertools

import gymnasium as gym
import numpy as np
import pytest

from d2a_agents.deploy import DeploymentLoop, SimCameras, SimRobot
from d2a_agents.policy.agent import PolicyConfig
from d2a_agents.policy.checkpoints import CHECKPOINT_NAME
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.train import TrainPolicyConfig, train_policy
from d2a_envs.rgbd import fuse_frames
from d2a_envs.wrappers import IMAGINED_KEY

ENV_KWARGS = {"image_size": 48, "num_points": 128}  # the conftest's reach_data settings


def _checkpoint(reach_data, out, algo="mp1", world_model=None) -> str:
    policy = PolicyConfig(algo=algo, num_points=64, encoder=EncoderConfig(point_widths=(16, 32)),
                          network=VelocityNetConfig(hidden=32, layers=2))
    train_policy(TrainPolicyConfig(data=reach_data, out=str(out), policy=policy, world_model=world_model, steps=2,
                                   batch_size=4, eval_episodes=0, progress=False))
    return str(out / CHECKPOINT_NAME)


class FakeClock:
    """Advances ``tick`` seconds per reading; records the sleeps."""

    def __init__(self, tick: float) -> None:
        self.times, self.slept = itertools.count(0.0, tick), []

    def __call__(self) -> float:
        return next(self.times)

    def sleep(self, seconds: float) -> None:
        self.slept.append(seconds)


@pytest.fixture
def sim():
    env = gym.make("D2A-MetaWorld-Reach-v0", **ENV_KWARGS)
    robot, cameras = SimRobot(env, seed=3), SimCameras(env)
    yield env, robot, cameras
    cameras.close()
    env.close()


def test_the_loop_observes_the_training_cloud_and_applies_one_action_per_period(reach_data, tmp_path, sim):
    env, robot, cameras = sim
    clock = FakeClock(0.01)  # four readings a step: 30 ms of work
    loop = DeploymentLoop(_checkpoint(reach_data, tmp_path), cameras, robot, hz=10, clock=clock, sleep=clock.sleep)
    observation = loop.observe()
    assert observation["point_cloud"].shape == (128, 3) and observation["agent_pos"].shape == (4,)
    # The same cameras as the env's own sensor, in the checkpoint's box: the same points land in the crop.
    assert loop.crop_box == env.get_wrapper_attr("config").crop_box
    reading = fuse_frames(cameras.frames(), loop.crop_box, 128, np.random.default_rng(0))
    assert reading.num_in_crop == robot.info["num_points_in_crop"] > 128
    log = loop.run(steps=6)
    assert len(log.steps) == 6 and not log.interrupted
    assert env.get_wrapper_attr("_elapsed_steps") == 6  # six actions applied
    assert not any(step.late for step in log.steps) and len(clock.slept) == 6
    assert all(step.total == pytest.approx(0.03) for step in log.steps)
    assert "6 steps at 10 Hz" in log.summary() and "late steps 0 (0.0 %)" in log.summary()
    late = DeploymentLoop(_checkpoint(reach_data, tmp_path / "again"), cameras, robot, hz=50, clock=FakeClock(0.01),
                          sleep=lambda seconds: pytest.fail("a late loop must not sleep"))
    assert all(step.late for step in late.run(steps=3).steps)  # 30 ms of work in a 20 ms period


def test_a_pixel_stride_fuses_every_kth_pixel_only(reach_data, tmp_path, sim):
    from d2a_envs.rgbd import frame_points

    env, robot, cameras = sim
    checkpoint = _checkpoint(reach_data, tmp_path)
    cloud = DeploymentLoop(checkpoint, cameras, robot, pixel_stride=2).observe()["point_cloud"]
    frames = cameras.frames()
    read = np.concatenate([frame.depth[::2, ::2].reshape(-1) for frame in frames])
    strided = np.concatenate([frame_points(frame, pixel_stride=2) for frame in frames])
    assert len(strided) == np.count_nonzero(np.isfinite(read) & (read > 0))  # one point per valid read pixel
    others = np.concatenate([frame_points(frame)[~_on_even_pixels(frame)] for frame in frames])
    nearest = np.abs(cloud[:, None, :] - strided[None]).max(-1).min(1)
    assert cloud.shape == (128, 3) and nearest.max() < 1e-5  # every point from an even row and column
    assert np.abs(cloud[:, None, :] - others[None]).max(-1).min() > 1e-9  # none from an odd row or column
    with pytest.raises(ValueError, match="pixel_stride"):
        DeploymentLoop(checkpoint, cameras, robot, pixel_stride=0)


def _on_even_pixels(frame) -> np.ndarray:
    """Which of ``frame_points(frame)``'s points come from an even row and column."""
    depth = np.asarray(frame.depth, dtype=np.float64)
    rows, columns = np.indices(depth.shape)
    valid = np.isfinite(depth) & (depth > 0)
    return ((rows % 2 == 0) & (columns % 2 == 0))[valid]


def test_the_loop_acts_as_told(reach_data, tmp_path, sim):
    from d2a_agents.policy.checkpoints import Acting

    env, robot, cameras = sim
    checkpoint = _checkpoint(reach_data, tmp_path)
    loop = DeploymentLoop(checkpoint, cameras, robot, acting=Acting(n_action_steps=1, action_draws=3))
    assert (loop.policy.action_draws, loop.policy.config.executed_actions) == (3, 1)
    assert DeploymentLoop(checkpoint, cameras, robot).policy.action_draws == 1


def test_a_d2a_policy_imagines_from_the_actions_it_applied(reach_data, tmp_path, sim):
    from d2a_agents.world_model.train import TrainWorldModelConfig, train_world_model
    from d2a_agents.world_model.triplane import WorldModelConfig

    env, robot, cameras = sim
    wm = tmp_path / "wm.pt"
    model = WorldModelConfig(resolution=(16, 16, 8))
    train_world_model(TrainWorldModelConfig(data=reach_data, out=str(wm), model=model, steps=2, batch_size=2,
                                            queries=256, validate_every=2, validation_stride=20, progress=False))
    loop = DeploymentLoop(_checkpoint(reach_data, tmp_path / "d2a", "d2a", str(wm)), cameras, robot, hz=1000)
    seen, applied = [], []
    select, apply = loop.policy.select_action, robot.apply
    loop.policy.select_action = lambda observation: seen.append(observation) or select(observation)
    robot.apply = lambda action: applied.append(action) or apply(action)
    loop.run(steps=5)
    assert all(observation[IMAGINED_KEY].shape == (64, 3) for observation in seen)
    history = loop.imaginer.config.action_history
    expected = np.stack(([np.zeros(4)] * history + applied)[-history:])
    np.testing.assert_allclose(loop.history, expected)  # the last actions applied, oldest first


def test_ctrl_c_stops_the_robot_and_returns_the_log(reach_data, tmp_path, sim):
    env, robot, cameras = sim
    stopped, applied = [], []

    class Interrupting(SimRobot):
        def apply(self, action):
            if len(applied) == 2:
                raise KeyboardInterrupt
            applied.append(action)
            super().apply(action)

        def stop(self):
            stopped.append(True)

    loop = DeploymentLoop(_checkpoint(reach_data, tmp_path), cameras, Interrupting(env), hz=1000)
    log = loop.run()
    assert log.interrupted and len(log.steps) == 2 and stopped == [True]
    assert all(np.isfinite(action).all() for action in applied)


def test_d2a_act_runs_a_checkpoint_on_the_simulated_robot(reach_data, tmp_path, capsys):
    from d2a.cli import main

    main(["act", "--policy", _checkpoint(reach_data, tmp_path), "--steps", "4", "--hz", "1000", "--pixel-stride", "2",
          "--action-draws", "2"])
    out = capsys.readouterr().out
    assert "4 steps at 1000 Hz" in out and "the simulated reach reported success on" in out


def test_an_image_policy_is_refused_by_the_cloud_deployment_loop(tmp_path, sim):
    from collectors.collect import CollectConfig, collect

    env, robot, cameras = sim
    data = tmp_path / "data"
    collect(CollectConfig(tasks=("reach",), out=str(data), episodes=1, env_kwargs={**ENV_KWARGS, "rgb_image_size": 40},
                          progress=False))
    policy = PolicyConfig(algo="dp", encoder=EncoderConfig(image_widths=(4, 4, 4, 4)),
                          network=VelocityNetConfig(hidden=16, layers=1))
    train_policy(TrainPolicyConfig(data=str(data), out=str(tmp_path / "run"), policy=policy, steps=1, batch_size=2,
                                   eval_episodes=0, progress=False))
    with pytest.raises(ValueError, match="reads a camera image"):
        DeploymentLoop(str(tmp_path / "run" / CHECKPOINT_NAME), cameras, robot)


def test_an_oracle_policy_is_refused_by_the_robot_loop(reach_data, tmp_path, sim):
    _, robot, cameras = sim
    with pytest.raises(ValueError, match="true future"):
        DeploymentLoop(_checkpoint(reach_data, tmp_path, algo="d2a-oracle"), cameras, robot)


def test_a_trained_checkpoint_closes_the_drawer_through_the_loop(tmp_path):
    """The whole path to success: one demonstration, a small policy trained on it for 600 steps
    (enough for each of training seeds 0-2 to close the drawer of its demonstration's layout
    within about 100 steps, through the loop; 250 steps are not), then 200 steps of the loop
    on that layout with the simulated robot and cameras."""
    from collectors.collect import CollectConfig, collect

    data = tmp_path / "data"
    collect(CollectConfig(tasks=("drawer-close",), out=str(data), episodes=1, env_kwargs=ENV_KWARGS, progress=False))
    policy = PolicyConfig(algo="mp1", num_points=64, encoder=EncoderConfig(point_widths=(16, 32)),
                          network=VelocityNetConfig(hidden=64, layers=2))
    train_policy(TrainPolicyConfig(data=str(data), out=str(tmp_path / "run"), policy=policy, steps=600, batch_size=32,
                                   augment_shift=0.0, eval_episodes=0, progress=False))
    env = gym.make("D2A-MetaWorld-DrawerClose-v0", **ENV_KWARGS)
    robot, cameras = SimRobot(env.unwrapped, seed=0), SimCameras(env)  # seed 0: the demonstration's layout
    loop = DeploymentLoop(str(tmp_path / "run" / CHECKPOINT_NAME), cameras, robot, hz=1000)
    log = loop.run(steps=200)
    cameras.close()
    env.close()
    assert len(log.steps) == 200 and robot.successes > 0
