"""Steps an acting policy reads: the schedule against a simulated reader, and the env skipping the rest."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import d2a_envs
from d2a_envs.read_steps import ReadSteps
from tests.conftest import SMALL_ENV_KWARGS


def frames_a_chunking_reader_uses(period: int, window: int, steps: int) -> set[int]:
    """Play a reader that keeps its last ``window`` frames (the first one repeated after a reset)
    and plans whenever its queue of ``period`` actions runs out: the frames its plans look at."""
    history: list[int] = []
    queue = 0
    used: set[int] = set()
    for step in range(steps):
        history = ([step] * window if not history else history + [step])[-window:] if window else []
        if queue == 0:
            used.update(history)
            queue = period
        queue -= 1
    return used


@pytest.mark.parametrize("period, window", [(3, 2), (3, 1), (1, 2), (4, 2), (2, 3), (3, 0), (5, 5)])
def test_the_schedule_reads_exactly_the_frames_a_chunking_reader_plans_from(period, window):
    schedule = ReadSteps(period, window)
    used = frames_a_chunking_reader_uses(period, window, 40 + period)  # the plans after step 39 too
    assert {k for k in range(40) if schedule(k)} == {k for k in used if k < 40}


def test_a_schedule_covers_another_when_it_reads_every_step_the_other_reads():
    assert ReadSteps(3, 2).covers(ReadSteps(3, 1))
    assert not ReadSteps(3, 1).covers(ReadSteps(3, 2))
    assert ReadSteps().covers(ReadSteps(4, 3)) and ReadSteps(2, 1).covers(ReadSteps(4, 1))
    assert not ReadSteps(2, 1).covers(ReadSteps(3, 1))  # step 3
    assert ReadSteps(3, 0).covers(ReadSteps(5, 0))  # nothing read, nothing missed


def test_read_steps_come_from_pairs_and_mappings_and_refuse_the_rest():
    assert ReadSteps.from_any((3, 2)) == ReadSteps.from_any({"period": 3, "window": 2}) == ReadSteps(3, 2)
    assert ReadSteps.from_any(None) == ReadSteps(1, 1)
    with pytest.raises(TypeError, match="period, window"):
        ReadSteps.from_any(3)
    for period, window in ((0, 1), (2, -1), (1.5, 1), (True, 1)):
        with pytest.raises(ValueError, match="whole number"):
            ReadSteps(period, window)


def rollout(env: gym.Env, steps: int) -> tuple[list[np.ndarray], list[int]]:
    observation, info = env.reset(seed=3)
    clouds, counts = [observation["point_cloud"]], [info["num_points_in_crop"]]
    actions = np.random.default_rng(0).uniform(-1, 1, (steps, *env.action_space.shape)).astype(np.float32)
    for action in actions:
        observation, _, _, _, info = env.step(action)
        clouds.append(observation["point_cloud"])
        counts.append(info["num_points_in_crop"])
    return clouds, counts


def test_an_env_renders_the_steps_read_as_before_and_leaves_the_others_nan():
    env_id = d2a_envs.get_task("push").env_id
    schedule = ReadSteps(3, 2)
    every, every_count = rollout(gym.make(env_id, **SMALL_ENV_KWARGS), 8)
    read, read_count = rollout(gym.make(env_id, read_steps={"point_cloud": schedule}, **SMALL_ENV_KWARGS), 8)
    for step, (reference, cloud) in enumerate(zip(every, read, strict=True)):
        if schedule(step):
            np.testing.assert_array_equal(cloud, reference)  # the physics never saw the skipped renders
            assert read_count[step] == every_count[step] > 0
        else:
            assert cloud.shape == reference.shape and np.isnan(cloud).all() and read_count[step] == -1


def test_an_env_refuses_read_steps_for_an_observation_it_does_not_make():
    with pytest.raises(ValueError, match="point_cloud and imagined_point_cloud only"):
        d2a_envs.make_env("metaworld", "push-v3", read_steps={"image": (3, 1)}, **SMALL_ENV_KWARGS)
