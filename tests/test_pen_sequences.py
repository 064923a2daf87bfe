"""Pen's sequence library: angles, blending, the rollouts that score it, and its build."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium_robotics.utils.rotations import euler2quat

from benchmarks.pen_library import PenLibraryConfig, PenRollouts, build, hold_score, optimise
from collectors.pen_sequences import SequenceLibrary, target_roll_pitch
from d2a_envs.suites.adroit import AdroitEnv


def test_roll_and_pitch_are_read_back_from_the_envs_quaternion():
    for roll, pitch in np.random.default_rng(0).uniform(-1.0, 1.0, (20, 2)):
        assert target_roll_pitch(euler2quat(np.array([roll, pitch, 0.0]))) == pytest.approx((roll, pitch), abs=1e-9)


def linear_library(steps: int = 3) -> SequenceLibrary:
    """Sequences 2 roll - pitch + 0.1 t in every actuator: a bilinear blend reproduces them exactly."""
    library = SequenceLibrary.empty(nodes=5, steps=steps, actuators=2)
    roll, pitch, t = np.meshgrid(library.axis, library.axis, np.arange(steps), indexing="ij")
    library.sequences[:] = (2 * roll - pitch + 0.1 * t)[..., None]
    return library


def test_the_nearest_node_is_the_one_closest_in_angle():
    library = linear_library()
    rng = np.random.default_rng(3)
    for roll, pitch, step in zip(*rng.uniform(-1.2, 1.2, (2, 20)), rng.integers(0, 5, 20), strict=True):
        i, j = np.abs(library.axis - roll).argmin(), np.abs(library.axis - pitch).argmin()  # angles beyond clamp
        expected = 2 * library.axis[i] - library.axis[j] + 0.1 * min(step, 2)  # the last step held
        assert library.action(roll, pitch, step) == pytest.approx([expected] * 2)
    assert library.action(0.3, -0.7, 1) == pytest.approx([2 * 0.5 + 0.5 + 0.1] * 2)
    assert np.array_equal(library.sequence(0.3, -0.7), np.stack([library.action(0.3, -0.7, t) for t in range(3)]))


def test_the_blend_of_the_four_nodes_around_a_target_matches_a_hand_computation():
    library = linear_library()
    assert library.action(0.3, -0.7, 1, blend=True) == pytest.approx([2 * 0.3 + 0.7 + 0.1] * 2)
    assert library.action(5.0, -5.0, 1, blend=True) == pytest.approx([2 * 1.0 + 1.0 + 0.1] * 2)  # clamped
    assert library.action(0.0, 0.0, 99, blend=True) == pytest.approx([0.2] * 2)  # the last step held
    assert np.array_equal(library.sequence(0.3, -0.7, blend=True),
                          np.stack([library.action(0.3, -0.7, t, blend=True) for t in range(3)]))
    # a hand bilinear blend of arbitrary corner values
    library.sequences[:] = np.random.default_rng(1).normal(size=library.sequences.shape)
    u, v = (0.3 + 1.0) / 0.5 - 2, (-0.7 + 1.0) / 0.5 - 0  # cell (2, 0) of a 0.5-rad grid
    c = library.sequences[2:4, 0:2, 1]
    expected = (1 - u) * (1 - v) * c[0, 0] + (1 - u) * v * c[0, 1] + u * (1 - v) * c[1, 0] + u * v * c[1, 1]
    assert library.action(0.3, -0.7, 1, blend=True) == pytest.approx(expected)


def test_an_unfinished_library_is_refused_and_a_saved_one_reads_back(tmp_path):
    library = linear_library()
    library.sequences[1, 2] = np.nan
    with pytest.raises(ValueError, match="1 unsolved"):
        library.action(0.0, 0.0, 0)
    library.save(tmp_path / "lib.npz")
    back = SequenceLibrary.load(tmp_path / "lib.npz")
    assert np.array_equal(back.solved, library.solved) and np.array_equal(back.axis, library.axis)
    assert np.allclose(back.sequences[back.solved], library.sequences[library.solved], atol=1e-6)


def test_the_rollouts_see_what_the_env_shows(tmp_path):
    """The orientation and distance the build scores, against the env stepped action by action
    and read from its own sites."""
    rollouts = PenRollouts()
    sequence = np.clip(np.random.default_rng(2).normal(0.0, 0.4, (1, 12, len(rollouts.actuator_names))), -1, 1)
    dot, distance = rollouts.measure(sequence, 0.4, -0.3)
    env = AdroitEnv("pen", state_obs=False)
    env.reset(seed=0)
    env.model.body_quat[env.model.body("target").id] = euler2quat(np.array([0.4, -0.3, 0.0]))
    site = {name: env.model.site(name).id for name in ("object_top", "object_bottom", "target_top", "target_bottom",
                                                         "eps_ball")}
    for step, action in enumerate(sequence[0]):
        env.step(action)
        x = env.data.site_xpos
        pen, target = x[site["object_top"]] - x[site["object_bottom"]], x[site["target_top"]] - x[site["target_bottom"]]
        cosine = pen @ target / np.linalg.norm(pen) / np.linalg.norm(target)
        centre = env.data.xpos[env.model.body("Object").id]
        assert dot[0, step] == pytest.approx(cosine, abs=1e-6)
        assert distance[0, step] == pytest.approx(np.linalg.norm(centre - x[site["eps_ball"]]), abs=1e-6)
    env.close()


def test_the_search_never_scores_worse_than_its_start():
    rollouts = PenRollouts()
    config = PenLibraryConfig(steps=8, iterations=2, samples=3, knots=2, hold_steps=4)
    start = np.zeros((8, len(rollouts.actuator_names)))
    best = optimise(rollouts, start, 0.2, 0.1, config, np.random.default_rng(0))

    def score(sequence: np.ndarray) -> float:
        return float(hold_score(*rollouts.measure(sequence[None], 0.2, 0.1), 4)[0]
                     + config.tracking * ((sequence - start) ** 2).mean())

    assert score(best) <= score(start)


def test_a_tiny_build_solves_every_node_and_a_rerun_resumes_without_redoing_them(tmp_path):
    config = PenLibraryConfig(out=str(tmp_path / "lib.npz"), nodes=2, steps=6, iterations=1, samples=2, knots=2,
                              hold_steps=3, check_layouts=2)
    library = build(config)
    assert library.solved.all() and (library.attempts >= 1).all()
    again = build(config)
    assert np.array_equal(again.sequences, SequenceLibrary.load(config.out).sequences)
    assert np.array_equal(again.attempts, library.attempts)
    with pytest.raises(ValueError, match="choose another --out"):
        build(PenLibraryConfig(out=config.out, nodes=3, steps=6, hold_steps=3))
