"""The D2A Gymnasium environments: geometry against simulator truth, seeding, spaces, errors."""

from __future__ import annotations

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import d2a_envs
from d2a_envs.camera import camera_id
from d2a_envs.depth import RaycastDepth, RenderDepth
from tests.conftest import requires_render

SMALL = dict(image_size=64, num_points=128)  # fast settings for tests that do not look at geometry


def make(task: str, **kwargs) -> gym.Env:
    return gym.make(d2a_envs.get_task(task).env_id, **kwargs)


@pytest.mark.parametrize("task", ["hammer", "push", "assembly", "basketball", "shelf-place"])
def test_cloud_has_points_on_the_object_and_the_fingers(task):
    """The object position comes from the state observation and the finger pads from MuJoCo
    bodies: neither goes through the camera code."""
    env = make(task)
    for seed in (0, 1):
        observation, _ = env.reset(seed=seed)
        cloud, state = observation["point_cloud"], observation["state"]
        object_distance = np.linalg.norm(cloud - state[4:7], axis=1)
        # Body origins sit inside the objects: the nearest visible surface is a few cm away.
        assert object_distance.min() < 0.03, f"{task} seed {seed}: no point near the object"
        assert (object_distance < 0.05).sum() >= 5
        data = env.unwrapped.data
        for pad in ("leftpad", "rightpad"):
            pad_distance = np.linalg.norm(cloud - data.body(pad).xpos, axis=1)
            assert pad_distance.min() < 0.02, f"{task}: no point near the gripper's {pad}"
    env.close()


@pytest.mark.parametrize("task", ["push", "stick-pull", "lever-pull"])
def test_goal_marker_is_in_the_cloud_from_the_first_frame(task):
    """The goal comes from the task's own target (simulator truth), not from the camera code;
    the first frame already shows the marker there, and ``show_sites=False`` removes it."""
    for show_sites, expected in ((True, True), (False, False)):
        env = make(task, show_sites=show_sites)
        for seed in (0, 1):
            observation, _ = env.reset(seed=seed)
            goal = env.unwrapped._sim._target_pos
            near_goal = np.linalg.norm(observation["point_cloud"] - goal, axis=1) < 0.025
            assert near_goal.any() == expected, f"{task} seed {seed} show_sites={show_sites}"
        env.close()


def test_cloud_follows_the_moving_gripper():
    env = make("reach")
    observation, _ = env.reset(seed=0)
    old_hand, before = observation["agent_pos"][:3], observation["point_cloud"]
    for _ in range(15):
        observation, *_ = env.step(np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32))  # move +x
    new_hand, after = observation["agent_pos"][:3], observation["point_cloud"]
    assert new_hand[0] - old_hand[0] > 0.05

    def near(cloud, point):
        return int((np.linalg.norm(cloud - point, axis=1) < 0.06).sum())

    assert near(after, new_hand) >= 5
    assert near(after, old_hand) < near(before, old_hand)


def test_same_seed_same_cloud_different_seed_different_layout():
    env = make("push", **SMALL)
    first, _ = env.reset(seed=7)
    env.step(env.action_space.sample())
    again, _ = env.reset(seed=7)
    other, _ = env.reset(seed=8)
    np.testing.assert_array_equal(first["point_cloud"], again["point_cloud"])
    np.testing.assert_array_equal(first["state"], again["state"])
    assert not np.allclose(first["state"][4:7], other["state"][4:7])  # the puck moved
    assert not np.array_equal(first["point_cloud"], other["point_cloud"])


def test_unseeded_resets_give_new_layouts():
    env = make("push", **SMALL)
    env.reset(seed=0)
    positions = {tuple(env.reset()[0]["state"][4:7].round(4)) for _ in range(3)}
    assert len(positions) == 3


def test_a_crop_box_of_six_numbers_is_two_corners():
    env = make("hammer", crop_box=[-0.6, 0.25, 0.005, 0.6, 0.97, 0.7], **SMALL)
    expected = d2a_envs.make_env("metaworld", "hammer-v3", crop_box=((-0.6, 0.25, 0.005), (0.6, 0.97, 0.7)), **SMALL)
    observation, _ = env.reset(seed=0)
    reference, _ = expected.reset(seed=0)
    np.testing.assert_array_equal(observation["point_cloud"], reference["point_cloud"])


def test_points_respect_a_custom_crop_box_and_fill_by_resampling():
    box = ((-0.1, 0.5, 0.02), (0.1, 0.7, 0.2))  # a small box around the hand's start
    env = make("push", crop_box=box, num_points=2048)
    observation, info = env.reset(seed=0)
    cloud = observation["point_cloud"]
    assert cloud.shape == (2048, 3)
    assert np.all(cloud >= np.array(box[0], dtype=np.float32)) and np.all(cloud <= np.array(box[1], dtype=np.float32))
    assert 0 < info["num_points_in_crop"] < 2048
    assert len(np.unique(cloud, axis=0)) == info["num_points_in_crop"]  # repeats, never invented points



def _table_top_under(sim, xy: np.ndarray) -> float:
    """The top of the table's box geoms under ``xy``, read from the MuJoCo model (not the crop code)."""
    model, data = sim.model, sim.data
    table = model.body("tablelink").id
    tops = [data.geom_xpos[g][2] + model.geom_size[g][2] for g in range(model.ngeom)
            if model.geom_bodyid[g] == table and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX
            and np.all(np.abs(xy - data.geom_xpos[g][:2]) <= model.geom_size[g][:2])]
    return max(tops)


@pytest.mark.parametrize("task", ["push", "hand-insert", "sweep-into"])
def test_the_crop_floor_is_5_mm_above_the_table_top_under_the_object(task):
    """Hand-Insert and Sweep-Into stand on a table top at z = 5 cm: a floor at 5 mm kept that
    top, about 80 % of the points, and left the block none of 128."""
    env = make(task)
    observation, _ = env.reset(seed=0)
    floor = env.get_wrapper_attr("config").crop_box.low[2]
    assert floor == pytest.approx(_table_top_under(env.unwrapped._sim, observation["state"][4:6]) + 0.005)
    cloud = observation["point_cloud"]
    assert (cloud[:, 2] < floor + 0.01).mean() < 0.2
    assert (np.linalg.norm(cloud - observation["state"][4:7], axis=1) < 0.04).sum() >= 5
    env.close()

def test_rgb_points():
    env = make("hammer", with_rgb=True, **SMALL)
    observation, _ = env.reset(seed=0)
    cloud = observation["point_cloud"]
    assert cloud.shape == (128, 6)
    assert env.observation_space.contains(observation)
    assert np.all((cloud[:, 3:] >= 0) & (cloud[:, 3:] <= 1)) and cloud[:, 3:].std() > 0


def _robot_red(image: np.ndarray) -> np.ndarray:
    """Pixels of the Sawyer's red links, lit or in shade: red well above green and blue."""
    red, green, blue = (image[..., channel].astype(int) for channel in range(3))
    return (red > 40) & (red > 1.6 * green) & (red > 1.6 * blue)


@requires_render
def test_the_image_observation_is_the_cameras_view():
    """The render backend's image is what MuJoCo's own renderer draws from that camera; the
    raycast image (an independent projection: one ray per pixel) shows the robot where it does."""
    import mujoco

    render_env = make("hammer", rgb_image_size=64, backend="render", **SMALL)
    image = render_env.reset(seed=0)[0]["image"]
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    assert render_env.observation_space.contains(render_env.reset(seed=0)[0])
    base = render_env.unwrapped
    renderer = mujoco.Renderer(base.model, 64, 64)
    renderer.update_scene(base.data, camera="corner4")
    for effect in ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_SKYBOX"):  # left out of the image, for speed
        renderer.scene.flags[getattr(mujoco.mjtRndFlag, effect)] = False
    assert np.abs(renderer.render().astype(int) - image.astype(int)).max() <= 1
    renderer.close()
    raycast_image = make("hammer", rgb_image_size=64, **SMALL).reset(seed=0)[0]["image"]
    drawn, cast = _robot_red(image), _robot_red(raycast_image)
    assert drawn.sum() > 100
    assert (drawn & cast).sum() / (drawn | cast).sum() > 0.8
    render_env.close()


def test_images_only_when_asked_and_of_a_usable_size():
    assert "image" not in make("hammer", **SMALL).reset(seed=0)[0]
    env = make("adroit-door", rgb_image_size=40, **SMALL)
    observation, _ = env.reset(seed=0)
    assert observation["image"].shape == (40, 40, 3) and observation["image"].std() > 0
    assert env.observation_space.contains(env.step(env.action_space.sample())[0])
    with pytest.raises(ValueError, match="at least 8 pixels"):
        make("hammer", rgb_image_size=4, **SMALL)


@pytest.mark.parametrize("task", ["hammer", "adroit-door"])
def test_dict_space_contains_every_observation(task):
    env = make(task, **SMALL)
    observation, info = env.reset(seed=0)
    assert set(observation) == {"point_cloud", "agent_pos", "state"}
    assert env.observation_space.contains(observation)
    assert info["success"] is False
    schema = {key: type(value) for key, value in info.items()}
    for _ in range(3):
        observation, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(observation)
        assert isinstance(info["success"], bool)
        # one info schema at reset and at every step: vectorised envs batch it without masks
        assert {key: type(value) for key, value in info.items()} == schema


def test_state_can_be_left_out():
    env = make("hammer", state_obs=False, **SMALL)
    observation, _ = env.reset(seed=0)
    assert set(observation) == {"point_cloud", "agent_pos"}


def test_default_episode_is_200_steps_and_configurable():
    env = make("reach", max_episode_steps=3, **SMALL)
    env.reset(seed=0)
    truncations = [env.step(env.action_space.sample())[3] for _ in range(3)]
    assert truncations == [False, False, True]
    assert gym.spec("D2A-MetaWorld-Reach-v0").max_episode_steps == 200


def test_episodes_longer_than_metaworlds_own_limit():
    env = make("reach", max_episode_steps=510, image_size=16, num_points=8)
    env.reset(seed=0)
    for step in range(1, 511):  # Meta-World itself raises after 500 steps
        *_, truncated, _ = env.step(env.action_space.sample())
        assert truncated == (step == 510)


@pytest.mark.parametrize("task", ["hammer", "adroit-pen"])
def test_gymnasium_env_checker(task):
    spec = d2a_envs.get_task(task)
    check_env(d2a_envs.make_env(spec.suite, spec.task, **SMALL), skip_render_check=True)


@pytest.mark.parametrize("vector_class", [gym.vector.SyncVectorEnv, gym.vector.AsyncVectorEnv])
def test_vector_envs(vector_class):
    envs = vector_class([lambda: make("hammer", **SMALL) for _ in range(2)])
    observations, infos = envs.reset(seed=[0, 1])
    assert observations["point_cloud"].shape == (2, 128, 3)
    observations, rewards, terminated, truncated, infos = envs.step(envs.action_space.sample())
    assert observations["point_cloud"].shape == (2, 128, 3)
    assert infos["success"].shape == (2,)
    envs.close()


def test_wrapper_records_its_constructor_args():
    env = make("hammer", **SMALL)
    recorded = env.spec.additional_wrappers if env.spec else ()
    pointcloud = env.get_wrapper_attr("config")
    assert pointcloud.num_points == 128
    assert env.env.env.env._saved_kwargs["config"] == pointcloud or any(
        w.name == "PointCloudObservation" for w in recorded
    )


@pytest.mark.parametrize("spec", d2a_envs.TASKS, ids=lambda spec: spec.env_id)
def test_every_registered_id_resets_and_steps(spec):
    env = gym.make(spec.env_id, image_size=32, num_points=64)
    observation, _ = env.reset(seed=0)
    assert observation["point_cloud"].shape == (64, 3)
    observation, *_ = env.step(env.action_space.sample())
    assert np.isfinite(observation["point_cloud"]).all()
    env.close()


def test_task_table():
    assert len(d2a_envs.list_tasks(suite="metaworld")) == 50
    assert len(d2a_envs.list_tasks(suite="adroit")) == 3
    counts = {level: len(d2a_envs.list_tasks(difficulty=level)) for level in ("easy", "medium", "hard", "very_hard")}
    assert counts == {"easy": 28, "medium": 11, "hard": 6, "very_hard": 5}
    assert d2a_envs.get_task("pick-place-wall").env_id == "D2A-MetaWorld-PickPlaceWall-v0"


def test_table1_tasks_are_the_papers_split():
    """Table I's 34 Meta-World tasks by group (DP3's / MP1's task configs), and the 3 Adroit ones."""
    split = {
        "easy": "button-press button-press-wall dial-turn door-close door-open door-unlock drawer-close "
                "faucet-close faucet-open handle-press handle-pull lever-pull peg-unplug-side plate-slide "
                "plate-slide-back plate-slide-back-side plate-slide-side reach reach-wall window-close window-open",
        "medium": "coffee-pull hammer peg-insert-side soccer",
        "hard": "assembly hand-insert pick-place push",
        "very_hard": "disassemble pick-place-wall shelf-place stick-pull stick-push",
    }
    for level, names in split.items():
        assert {spec.name for spec in d2a_envs.list_tasks(difficulty=level, table1=True)} == set(names.split())
    assert {spec.name for spec in d2a_envs.list_tasks(suite="adroit", table1=True)} == {
        "adroit-hammer", "adroit-door", "adroit-pen"}
    assert len(d2a_envs.list_tasks(table1=False)) == 50 - 34


# --- bad input gets a clear error -------------------------------------------------------


def test_unknown_task_suggests_close_ids():
    with pytest.raises(ValueError, match="did you mean hammer"):
        d2a_envs.get_task("hamer")
    with pytest.raises(gym.error.NameNotFound):
        gym.make("D2A-MetaWorld-Hamer-v0")


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(cameras=("nope",)), "unknown camera 'nope'; this model has cameras"),
        (dict(num_points=0), "num_points must be a positive integer"),
        (dict(num_points=2.5), "num_points must be a positive integer"),
        (dict(crop_box=(0, 0, 0, 1, 1)), "two corners of 3 numbers"),
        (dict(crop_box=((0, 0, 1), (1, 1, 0))), "inverted"),
        (dict(backend="vulkan"), "unknown depth backend"),
        (dict(crop_box=((5, 5, 5), (6, 6, 6))), "no point seen by cameras"),
    ],
)
def test_bad_configuration_is_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        env = make("hammer", **kwargs)
        env.reset(seed=0)


def test_nan_action_is_refused():
    env = make("hammer", **SMALL)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0, 0, 0], dtype=np.float32))


def test_render_backend_without_gl_says_what_to_install(monkeypatch):
    monkeypatch.setattr("d2a_envs.depth.bound_gl_platform", lambda: None)
    with pytest.raises(RuntimeError, match="apt-get install libegl1"):
        make("hammer", backend="render")


# --- the two depth backends agree -------------------------------------------------------


@requires_render
@pytest.mark.parametrize("task", ["hammer", "assembly", "shelf-place"])
@pytest.mark.parametrize("camera", ["corner4", "corner2", "topview"])
def test_backends_agree_within_2mm(task, camera):
    env = make(task, **SMALL)
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.action_space.sample())
    model, data = env.unwrapped.model, env.unwrapped.data
    cam = camera_id(model, camera)
    ray = RaycastDepth(128, 128).capture(model, data, cam, with_rgb=False).depth
    render = RenderDepth(128, 128).capture(model, data, cam, with_rgb=False).depth
    both = np.isfinite(ray) & np.isfinite(render)
    assert both.sum() > 1000
    agree = np.abs(ray[both] - render[both]) < 0.002
    assert agree.mean() >= 0.99
    seen_by_one = np.isfinite(ray) ^ np.isfinite(render)
    assert seen_by_one.mean() < 0.01


def _render_in_child(queue) -> None:
    env = make("hammer", backend="render", **SMALL)
    try:
        env.reset(seed=0)
        queue.put("rendered")
    except RuntimeError as error:
        queue.put(str(error))


@requires_render
def test_render_after_fork_of_a_rendering_parent_is_refused_not_hung():
    import multiprocessing

    parent_env = make("hammer", backend="render", **SMALL)
    parent_env.reset(seed=0)  # the parent now owns a GL context
    context = multiprocessing.get_context("fork")
    queue = context.Queue()
    child = context.Process(target=_render_in_child, args=(queue,))
    child.start()
    message = queue.get(timeout=60)
    child.join(timeout=60)
    assert "context='spawn'" in message


def test_an_action_held_for_two_steps_is_two_steps_of_the_simulator():
    held, plain = make("adroit-door", action_repeat=2, **SMALL), make("adroit-door", **SMALL)
    held.reset(seed=0)
    plain.reset(seed=0)
    action = np.random.default_rng(0).uniform(-1, 1, held.action_space.shape).astype(np.float32)
    observation, reward, *_ = held.step(action)
    first_reward = plain.step(action)[1]
    expected, second_reward, *_ = plain.step(action)
    np.testing.assert_array_equal(observation["state"], expected["state"])
    np.testing.assert_array_equal(observation["agent_pos"], expected["agent_pos"])
    assert reward == pytest.approx(first_reward + second_reward)
    with pytest.raises(ValueError, match="whole number"):
        make("adroit-door", action_repeat=0, **SMALL)


def test_a_held_action_succeeds_when_any_held_step_does():
    from d2a_envs.wrappers import ActionRepeat

    class Scripted(gym.Env):
        observation_space, action_space = gym.spaces.Discrete(1), gym.spaces.Discrete(1)

        def __init__(self) -> None:
            self.verdicts = iter([False, True, False, False, False, False])

        def step(self, action):
            return 0, 1.0, False, False, {"success": next(self.verdicts)}

    env = ActionRepeat(Scripted(), 3)
    assert env.step(0)[1:] == (3.0, False, False, {"success": True})  # held steps 1-3: the second succeeded
    assert env.step(0)[4] == {"success": False}


@requires_render
def test_a_render_env_left_open_exits_without_gl_errors():
    """MuJoCo terminates the EGL display at exit; a renderer still open then used to raise
    EGLError from its finaliser during interpreter shutdown (printed, not fatal)."""
    import subprocess
    import sys

    script = ("import gymnasium as gym, d2a_envs\n"
              "env = gym.make('D2A-MetaWorld-Reach-v0', backend='render', image_size=64, num_points=128)\n"
              "env.reset(seed=0)\n")
    finished = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert finished.returncode == 0, finished.stderr
    assert "Exception ignored" not in finished.stderr, finished.stderr


@requires_render
def test_a_software_renderer_drawing_in_the_calling_thread_gives_the_same_clouds():
    """``software_render_threads(1)`` makes llvmpipe draw in the calling thread (LP_NUM_THREADS=0):
    a speed setting only, so the clouds must equal those of its thread pool, bit for bit."""
    import os
    import subprocess
    import sys

    script = ("import gymnasium as gym, numpy as np, sys, d2a_envs\n"
              "from d2a_envs.gl import software_render_threads\n"
              "print('LP_NUM_THREADS=' + software_render_threads(1), file=sys.stderr)\n"
              "env = gym.make('D2A-MetaWorld-Push-v0', backend='render', image_size=96, num_points=512)\n"
              "clouds = [env.reset(seed=1)[0]['point_cloud']]\n"
              "clouds += [env.step(env.action_space.sample() * 0 + 0.5)[0]['point_cloud'] for _ in range(5)]\n"
              "sys.stdout.buffer.write(np.stack(clouds).tobytes())\n")
    clouds, chosen = [], []
    for pool in (None, "3"):  # ours, then a user's choice of 3 rasteriser threads, which it keeps
        env = {key: value for key, value in os.environ.items() if key != "LP_NUM_THREADS"}
        env |= {"LP_NUM_THREADS": pool} if pool else {}
        finished = subprocess.run([sys.executable, "-c", script], capture_output=True, env=env, timeout=120)
        assert finished.returncode == 0, finished.stderr.decode()
        clouds.append(np.frombuffer(finished.stdout, dtype=np.float32))
        chosen += [line for line in finished.stderr.decode().splitlines() if line.startswith("LP_NUM_THREADS=")]
    assert chosen == ["LP_NUM_THREADS=0", "LP_NUM_THREADS=3"]
    assert clouds[0].size == 6 * 512 * 3 and np.array_equal(clouds[0], clouds[1])
