"""RGB-D frames fused into observations: back-projection by hand, two simulated cameras (one
carried by the gripper) through the real-camera path against the env's own cloud, and the
eye-in-hand pose chain against MuJoCo's camera pose."""

from __future__ import annotations

import copy

import gymnasium as gym
import mujoco
import numpy as np
import pytest

import d2a_envs  # noqa: F401  (registers the ids)
from d2a_envs.camera import camera_id
from d2a_envs.rgbd import (
    CameraIntrinsics,
    RGBDFrame,
    eye_in_hand_pose,
    frame_points,
    fuse_frames,
    mujoco_frame,
    pose_matrix,
)
from d2a_envs.sampling import CropBox


def test_frame_points_by_hand():
    """A 2 x 3 image in millimetres; pixel (u, v) at depth z lies at ((u - cx) z / fx, (v - cy) z / fy, z)."""
    depth = np.array([[1000, 0, 2000], [500, 1500, np.nan]])
    intrinsics = CameraIntrinsics(fx=2.0, fy=4.0, cx=1.0, cy=0.5)
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    frame = RGBDFrame(depth, intrinsics, pose_matrix(rotation, np.array([0.1, 0.2, 0.3])), depth_scale=0.001)
    camera = np.array([[(0 - 1) * 1.0 / 2, (0 - 0.5) * 1.0 / 4, 1.0],      # (u 0, v 0), 1 m
                       [(2 - 1) * 2.0 / 2, (0 - 0.5) * 2.0 / 4, 2.0],      # (u 2, v 0), 2 m; (u 1, v 0) has no reading
                       [(0 - 1) * 0.5 / 2, (1 - 0.5) * 0.5 / 4, 0.5],      # (u 0, v 1)
                       [(1 - 1) * 1.5 / 2, (1 - 0.5) * 1.5 / 4, 1.5]])     # (u 1, v 1); (u 2, v 1) is NaN
    expected = np.stack([-camera[:, 1], camera[:, 0], camera[:, 2]], axis=1) + [0.1, 0.2, 0.3]
    np.testing.assert_allclose(frame_points(frame), expected, atol=1e-12)
    coloured = RGBDFrame(depth, intrinsics, np.eye(4), rgb=np.full((2, 3, 3), 255.0), depth_scale=0.001)
    assert frame_points(coloured, with_rgb=True).shape == (4, 6) and frame_points(coloured, True)[:, 3:].max() == 1.0
    with pytest.raises(ValueError, match="colour"):
        frame_points(frame, with_rgb=True)


def test_fuse_frames_crops_and_samples_to_exactly_n_points():
    rng = np.random.default_rng(0)
    frame = RGBDFrame(np.full((20, 30), 1.0), CameraIntrinsics(30.0, 30.0, 14.5, 9.5), np.eye(4))
    box = CropBox((-0.2, -0.2, 0.0), (0.2, 0.2, 2.0))
    reading = fuse_frames([frame, frame], box, 64, rng)
    assert reading.points.shape == (64, 3) and reading.points.dtype == np.float32
    assert reading.num_in_crop == 2 * int(np.sum((np.abs((np.arange(30) - 14.5) / 30) <= 0.2)[None, :]
                                                 & (np.abs((np.arange(20) - 9.5) / 30) <= 0.2)[:, None]))
    with pytest.raises(ValueError, match="no point seen by 1 frame"):
        fuse_frames([frame], CropBox((5, 5, 5), (6, 6, 6)), 64, rng)
    with pytest.raises(ValueError, match="at least one frame"):
        fuse_frames([], box, 64, rng)
    with pytest.raises(ValueError, match="4x4"):
        RGBDFrame(np.ones((2, 2)), CameraIntrinsics(1, 1, 0, 0), np.eye(3))


@pytest.fixture(scope="module")
def two_camera_env():
    """Hammer seen by a fixed camera and the one the gripper carries, after the arm has moved."""
    env = gym.make("D2A-MetaWorld-Hammer-v0", cameras=("corner2", "gripperPOV"), image_size=48, num_points=256)
    env.reset(seed=0)
    for _ in range(5):
        env.step(np.array([0.5, -0.3, 0.2, 0.0], dtype=np.float32))
    yield env
    env.close()


def test_two_simulated_cameras_through_the_real_path_give_the_envs_cloud(two_camera_env):
    base = two_camera_env.unwrapped
    sensor = two_camera_env.get_wrapper_attr("sensor")
    frames = []
    for name in ("corner2", "gripperPOV"):
        cam = camera_id(base.model, name)
        image = sensor._backend.capture(base.model, base.data, cam, with_rgb=False)
        frames.append(mujoco_frame(base.model, base.data, cam, image.depth))
    fused = np.concatenate([frame_points(frame) for frame in frames])
    expected = sensor.fused_points(base.model, base.data)
    # The same depths through two formulas in float64: any difference is round-off, far below 1 um.
    assert fused.shape == expected.shape and len(fused) > 1000
    np.testing.assert_allclose(fused, expected, atol=1e-9)


def test_the_eye_in_hand_pose_chain_is_mujocos_camera_pose(two_camera_env):
    """The gripper camera, rigidly fixed to the hand (Meta-World's tracks it in world axes): its
    pose is the hand's pose from the state times its fixed pose on the hand."""
    base = two_camera_env.unwrapped
    model = copy.deepcopy(base.model)
    cam = camera_id(model, "gripperPOV")
    model.cam_mode[cam] = mujoco.mjtCamLight.mjCAMLIGHT_FIXED
    data = mujoco.MjData(model)
    data.qpos[:] = base.data.qpos
    mujoco.mj_forward(model, data)
    body = model.cam_bodyid[cam]
    assert model.body(body).name == "hand"
    base_from_hand = pose_matrix(data.xmat[body].reshape(3, 3), data.xpos[body])
    local = np.zeros(9)
    mujoco.mju_quat2Mat(local, model.cam_quat[cam])
    # The hand-eye calibration: the camera's fixed pose on the hand, in OpenCV's axes.
    hand_from_camera = pose_matrix(local.reshape(3, 3) @ np.diag([1.0, -1.0, -1.0]), model.cam_pos[cam])
    expected = pose_matrix(data.cam_xmat[cam].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0]), data.cam_xpos[cam])
    np.testing.assert_allclose(eye_in_hand_pose(base_from_hand, hand_from_camera), expected, atol=1e-9)
    assert not np.allclose(base_from_hand[:3, 3], expected[:3, 3])  # the chain is not the identity


def test_a_pixel_stride_reads_every_kth_pixel():
    depth = np.arange(1, 13, dtype=float).reshape(3, 4)
    frame = RGBDFrame(depth, CameraIntrinsics(1.0, 1.0, 0.0, 0.0), np.eye(4))
    # Pixels (u, v) = (0, 0), (2, 0), (0, 2), (2, 2) at depths 1, 3, 9, 11.
    expected = [[0.0, 0.0, 1.0], [2 * 3.0, 0.0, 3.0], [0.0, 2 * 9.0, 9.0], [2 * 11.0, 2 * 11.0, 11.0]]
    np.testing.assert_allclose(frame_points(frame, pixel_stride=2), expected)
    with pytest.raises(ValueError, match="pixel_stride"):
        frame_points(frame, pixel_stride=0)
