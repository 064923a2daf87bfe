"""Crop box validation, farthest-point sampling and filling."""

from __future__ import annotations

import numpy as np
import pytest

from d2a_envs.sampling import CropBox, farthest_point_indices, sample_to_size


def exact_fps(points: np.ndarray, n_samples: int) -> np.ndarray:
    """Textbook O(N M) farthest-point sampling from index 0 (the reference)."""
    chosen = [0]
    distance = np.linalg.norm(points - points[0], axis=1)
    for _ in range(n_samples - 1):
        chosen.append(int(distance.argmax()))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return np.array(chosen)


def covering_radius(points: np.ndarray, sample: np.ndarray) -> float:
    """Largest distance from any point to its nearest sampled point."""
    return max(
        np.linalg.norm(points[i : i + 500, None] - sample[None], axis=2).min(axis=1).max()
        for i in range(0, len(points), 500)
    )


@pytest.mark.parametrize("seed", [0, 1])
def test_fps_covers_like_exact_fps_and_far_better_than_random(seed):
    rng = np.random.default_rng(seed)
    points = rng.random((3000, 3)).astype(np.float32)
    ours = farthest_point_indices(points, 512)
    assert len(set(ours.tolist())) == 512
    radius = covering_radius(points, points[ours])
    exact = covering_radius(points, points[exact_fps(points, 512)])
    random = covering_radius(points, points[rng.choice(3000, 512, replace=False)])
    assert radius <= 1.05 * exact
    assert radius < 0.7 * random


@pytest.mark.parametrize("n_points, n_samples", [(2, 1), (9, 8), (33, 31)])
def test_fps_on_tiny_clouds_matches_exact_fps(n_points, n_samples):
    points = np.random.default_rng(n_points).random((n_points, 3))
    ours = farthest_point_indices(points, n_samples)
    assert len(set(ours.tolist())) == n_samples
    exact = exact_fps(points, n_samples)
    assert covering_radius(points, points[ours]) <= 1.05 * covering_radius(points, points[exact]) + 1e-9


def test_fps_is_deterministic():
    points = np.random.default_rng(3).random((1000, 3))
    np.testing.assert_array_equal(farthest_point_indices(points, 100), farthest_point_indices(points, 100))


def test_fill_repeats_real_points_never_zeros():
    points = np.random.default_rng(0).random((10, 3)) + 5.0  # far from the origin
    filled = sample_to_size(points, 64, np.random.default_rng(0))
    assert filled.shape == (64, 3)
    np.testing.assert_array_equal(filled[:10], points)
    assert all(any(np.array_equal(row, p) for p in points) for row in filled)
    assert not np.any(np.all(filled == 0.0, axis=1))


def test_sampling_from_nothing_is_an_error():
    with pytest.raises(ValueError, match="empty"):
        sample_to_size(np.zeros((0, 3)), 8, np.random.default_rng(0))


@pytest.mark.parametrize(
    "low, high, message",
    [
        ((0, 0, 0), (1, 1, 0), r"inverted along \['z'\]"),
        ((0, 1, 0), (1, 0, 1), "inverted"),
        ((0, 0), (1, 1), "3 numbers"),
    ],
)
def test_bad_crop_boxes_are_refused(low, high, message):
    with pytest.raises(ValueError, match=message):
        CropBox(low=low, high=high)


def test_crop_box_bounds_are_inclusive():
    box = CropBox(low=(0, 0, 0), high=(1, 1, 1))
    points = np.array([[0, 0, 0], [1, 1, 1], [0.5, 0.5, 1.0001], [-0.0001, 0.5, 0.5]])
    np.testing.assert_array_equal(box.contains(points), [True, True, False, False])
