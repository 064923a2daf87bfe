"""Recorded episodes: a simulated episode recorded through the real-camera format (one fixed
camera, one on the hand), imported into a data set whose clouds are the env's own, and trained on."""

from __future__ import annotations

import copy

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import d2a_envs  # noqa: F401  (registers the ids)
from collectors.experts import ScriptedExpert
from collectors.recording import RecordedCamera, Recorder, import_recording
from collectors.storage import DatasetError, DemoDataset
from d2a.cli import main
from d2a_envs.camera import camera_id
from d2a_envs.depth import make_depth_backend
from d2a_envs.rgbd import CameraIntrinsics, mujoco_frame, pose_matrix

STEPS = 12


def _record(tmp_path, with_hand: bool):
    """A scripted Reach episode at 48 px: corner4's depth (and gripperPOV's, rigid on the hand)."""
    env = gym.make("D2A-MetaWorld-Reach-v0", image_size=48, num_points=128)
    observation, _ = env.reset(seed=0)
    base = env.unwrapped
    model = copy.deepcopy(base.model)  # the gripper camera rigidly on the hand, as a real wrist camera
    hand_cam, fixed_cam = camera_id(model, "gripperPOV"), camera_id(model, "corner4")
    model.cam_mode[hand_cam] = mujoco.mjtCamLight.mjCAMLIGHT_FIXED
    data = mujoco.MjData(model)
    depth = make_depth_backend("raycast", 48, 48, show_sites=True)

    def sync():
        data.qpos[:], data.qvel[:] = base.data.qpos, base.data.qvel
        data.mocap_pos[:], data.mocap_quat[:] = base.data.mocap_pos, base.data.mocap_quat
        mujoco.mj_forward(model, data)

    sync()
    fixed = mujoco_frame(model, data, fixed_cam, depth.capture(model, data, fixed_cam, False).depth)
    body = model.cam_bodyid[hand_cam]
    local = np.zeros(9)
    mujoco.mju_quat2Mat(local, model.cam_quat[hand_cam])
    cameras = {"corner4": RecordedCamera(fixed.intrinsics, fixed.pose)}
    if with_hand:
        hand_eye = pose_matrix(local.reshape(3, 3) @ np.diag([1.0, -1.0, -1.0]), model.cam_pos[hand_cam])
        cameras["wrist"] = RecordedCamera(fixed.intrinsics, hand_eye, mount="hand", depth_scale=0.001)
    recorder = Recorder(tmp_path / "rec", task="reach", cameras=cameras)
    expert, env_clouds = ScriptedExpert("reach"), []
    for _ in range(STEPS):
        sync()
        depths = {"corner4": depth.capture(model, data, fixed_cam, False).depth}
        if with_hand:
            wrist = depth.capture(model, data, hand_cam, False).depth
            depths["wrist"] = np.where(np.isfinite(wrist), np.round(wrist * 1000), 0).astype(np.uint16)  # mm
        hand_pose = pose_matrix(data.xmat[body].reshape(3, 3), data.xpos[body])
        action = np.clip(expert.expert.get_action(observation["state"].astype(np.float64)), -1, 1).astype(np.float32)
        recorder.add(depths, observation["agent_pos"], action, hand_pose=hand_pose)
        env_clouds.append(observation["point_cloud"])
        observation, *_ = env.step(action)
    recorder.end_episode()
    depth.close()
    env.close()
    return np.stack(env_clouds), env.get_wrapper_attr("config").crop_box


def test_a_recorded_fixed_camera_episode_imports_to_the_envs_own_clouds(tmp_path):
    env_clouds, box = _record(tmp_path, with_hand=False)
    dataset = import_recording(tmp_path / "rec", tmp_path / "data", crop_box=box, num_points=128)
    frames = DemoDataset.open_for_training(tmp_path / "data").frames()
    assert [(e.task, e.length) for e in dataset.metadata.episodes] == [("reach", STEPS)]
    # The same camera, crop and sampling as the env's sensor: the same clouds, up to round-off.
    np.testing.assert_allclose(frames["point_cloud"].numpy(), env_clouds, atol=1e-5)
    assert frames["action"].shape == (STEPS, 4) and frames["agent_pos"].shape == (STEPS, 4)


def test_a_hand_camera_recording_imports_and_trains(tmp_path):
    from d2a_agents.policy.agent import PolicyConfig
    from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
    from d2a_agents.policy.train import TrainPolicyConfig, train_policy

    _, box = _record(tmp_path, with_hand=True)
    main(["data", "import", "--recording", str(tmp_path / "rec"), "--out", str(tmp_path / "data"), "--num-points",
          "128"])  # the suite's crop box: the env's
    dataset = DemoDataset.open(tmp_path / "data")
    assert dataset.metadata.tasks["reach"]["num_points"] == 128
    policy = PolicyConfig(algo="mp1", num_points=32, encoder=EncoderConfig(point_widths=(8,)),
                          network=VelocityNetConfig(hidden=16, layers=1))
    _, history = train_policy(TrainPolicyConfig(data=str(tmp_path / "data"), out=str(tmp_path / "run"), policy=policy,
                                                steps=2, batch_size=4, eval_episodes=0, progress=False))
    assert history == []
    with pytest.raises(ValueError, match="another task or other cameras"):
        Recorder(tmp_path / "rec", task="push", cameras={"corner4": RecordedCamera(
            CameraIntrinsics(1.0, 1.0, 0.0, 0.0), np.eye(4))})
    with pytest.raises(DatasetError, match="not a recording"):
        import_recording(tmp_path / "nothing", tmp_path / "other", crop_box=box)

