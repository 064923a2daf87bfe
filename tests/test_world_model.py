"""The triplane world model: sampling, voxel grids, IoU metrics, losses, queries and data,
each checked against an independent (hand-written or brute-force) computation, plus an
end-to-end overfit of one real D2A transition."""

from __future__ import annotations

import dataclasses
import itertools
import math
from contextlib import contextmanager

import gymnasium as gym
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torch import nn

import d2a_envs
from d2a_agents.world_model.data import WorldModelTransitions
from d2a_agents.world_model.imagine import Imaginer, normalized_centres, predict_grid
from d2a_agents.world_model.losses import balanced_queries, focal_loss, near_band
from d2a_agents.world_model.metrics import IoUAccumulator, iou_from_counts, voxel_iou
from d2a_agents.world_model.triplane import (
    FEATURE_MODES,
    TriplaneWorldModel,
    VoxelDecoder,
    WorldModelConfig,
    positional_embedding,
    sample_plane,
    sample_volume,
)
from d2a_agents.world_model.voxels import VoxelGrid
from d2a_envs.sampling import CropBox


@contextmanager
def single_thread():
    """The CPU is shared: one intra-op thread avoids oversubscription in the training tests."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def centre_coordinate(i: float, n: int) -> float:
    """align_corners=False: cell i of n spans [-1, 1] / n, centred at (i + 0.5) / n * 2 - 1."""
    return (i + 0.5) / n * 2.0 - 1.0


# --------------------------------------------------------------------------------------------
# 1. sample_plane / sample_volume against hand-written bilinear / trilinear sampling
# --------------------------------------------------------------------------------------------

# A 2 x 3 plane (first axis 2 rows, second axis 3 columns) of distinct, non-affine values.
PLANE = torch.tensor([[1.0, 4.0, 9.0], [20.0, 50.0, 70.0]], dtype=torch.float64)


def bilinear_by_hand(values: torch.Tensor, u: float, v: float) -> float:
    """Textbook bilinear interpolation of a 2-D array; u runs along axis 0, v along axis 1."""
    rows, cols = values.shape
    pu, pv = (u + 1) / 2 * rows - 0.5, (v + 1) / 2 * cols - 0.5  # continuous cell index
    i0, j0 = math.floor(pu), math.floor(pv)
    du, dv = pu - i0, pv - j0
    assert 0 <= i0 < rows - 1 and 0 <= j0 < cols - 1, "keep the hand check away from the border"
    v00, v01 = values[i0, j0].item(), values[i0, j0 + 1].item()
    v10, v11 = values[i0 + 1, j0].item(), values[i0 + 1, j0 + 1].item()
    return (1 - du) * (1 - dv) * v00 + (1 - du) * dv * v01 + du * (1 - dv) * v10 + du * dv * v11


def plane_at(u: list[float], v: list[float], plane: torch.Tensor = PLANE) -> torch.Tensor:
    """Features (Q,) of a one-channel plane at the Q points (u[q], v[q])."""
    u_batch, v_batch = torch.tensor([u], dtype=torch.float64), torch.tensor([v], dtype=torch.float64)
    out = sample_plane(plane[None, None], u_batch, v_batch)
    assert out.shape == (1, len(u), 1)
    return out[0, :, 0]


def test_sample_plane_returns_the_cell_value_at_every_cell_centre():
    rows, cols = PLANE.shape
    cells = list(itertools.product(range(rows), range(cols)))
    u = [centre_coordinate(i, rows) for i, _ in cells]
    v = [centre_coordinate(j, cols) for _, j in cells]
    expected = torch.tensor([PLANE[i, j].item() for i, j in cells], dtype=torch.float64)
    torch.testing.assert_close(plane_at(u, v), expected)


def test_sample_plane_u_runs_along_the_first_axis():
    # Midway between the two rows (u = 0) at each column centre: the mean of the two rows.
    cols = PLANE.shape[1]
    v = [centre_coordinate(j, cols) for j in range(cols)]
    torch.testing.assert_close(plane_at([0.0] * cols, v), PLANE.mean(dim=0))
    # Midway between columns 0 and 1 (v = -1/3) on row 1: the mean of those two cells.
    torch.testing.assert_close(plane_at([centre_coordinate(1, 2)], [-1 / 3]),
                               torch.tensor([(20.0 + 50.0) / 2], dtype=torch.float64))
    # Moving u only changes the row: at u of row 1 and v of column 0 the value is PLANE[1, 0], not PLANE[0, 1].
    assert plane_at([centre_coordinate(1, 2)], [centre_coordinate(0, 3)]).item() == pytest.approx(20.0)


def test_sample_plane_matches_textbook_bilinear_at_arbitrary_points():
    points = [(-0.3, -0.45), (0.2, 0.1), (0.35, 0.55), (-0.49, 0.6), (0.0, -0.2)]
    u, v = [p[0] for p in points], [p[1] for p in points]
    expected = torch.tensor([bilinear_by_hand(PLANE, a, b) for a, b in points], dtype=torch.float64)
    torch.testing.assert_close(plane_at(u, v), expected)


def test_sample_plane_batches_and_channels_are_independent():
    planes = torch.stack([PLANE, PLANE.sqrt(), -PLANE**2])  # three channels
    batch = torch.stack([planes, planes + 100.0])  # (2, 3, 2, 3)
    u = torch.tensor([[0.2, -0.3], [0.35, 0.0]], dtype=torch.float64)
    v = torch.tensor([[0.1, -0.45], [0.55, -0.2]], dtype=torch.float64)
    out = sample_plane(batch, u, v)
    assert out.shape == (2, 2, 3)
    for b, q, c in itertools.product(range(2), range(2), range(3)):
        expected = bilinear_by_hand(batch[b, c], u[b, q].item(), v[b, q].item())
        assert out[b, q, c].item() == pytest.approx(expected)


def test_sample_volume_at_voxel_centres_and_axis_order():
    X, Y, Z = 2, 3, 4
    volume = (torch.arange(X * Y * Z, dtype=torch.float64) ** 1.5).reshape(1, 1, X, Y, Z)  # distinct values
    cells = list(itertools.product(range(X), range(Y), range(Z)))
    xyz = torch.tensor([[centre_coordinate(i, X), centre_coordinate(j, Y), centre_coordinate(k, Z)]
                        for i, j, k in cells], dtype=torch.float64)[None]
    out = sample_volume(volume, xyz)
    assert out.shape == (1, len(cells), 1)
    expected = torch.tensor([volume[0, 0, i, j, k].item() for i, j, k in cells], dtype=torch.float64)
    torch.testing.assert_close(out[0, :, 0], expected)
    # x = 0 lies midway between the two x slices: the mean over the first axis.
    mid = torch.tensor([[[0.0, centre_coordinate(2, Y), centre_coordinate(1, Z)]]], dtype=torch.float64)
    assert sample_volume(volume, mid).item() == pytest.approx(volume[0, 0, :, 2, 1].mean().item())
    # Trilinear at an interior point, written out by hand.
    x, y, z = 0.2, -0.1, 0.3
    p = [(c + 1) / 2 * n - 0.5 for c, n in zip((x, y, z), (X, Y, Z), strict=True)]
    base = [math.floor(c) for c in p]
    frac = [c - b for c, b in zip(p, base, strict=True)]
    expected_value = 0.0
    for di, dj, dk in itertools.product((0, 1), repeat=3):
        weight = ((frac[0] if di else 1 - frac[0]) * (frac[1] if dj else 1 - frac[1])
                  * (frac[2] if dk else 1 - frac[2]))
        expected_value += weight * volume[0, 0, base[0] + di, base[1] + dj, base[2] + dk].item()
    point = torch.tensor([[[x, y, z]]], dtype=torch.float64)
    assert sample_volume(volume, point).item() == pytest.approx(expected_value)


# --------------------------------------------------------------------------------------------
# 2. VoxelGrid
# --------------------------------------------------------------------------------------------

BOX = CropBox(low=(-0.6, 0.25, 0.005), high=(0.6, 0.97, 0.7))


@pytest.mark.parametrize("resolution", [(5, 7, 3), (16, 8, 4), (1, 1, 1)])
def test_voxelize_of_occupied_centres_is_the_identity(resolution):
    grid = VoxelGrid(BOX, resolution)
    generator = torch.Generator().manual_seed(sum(resolution))
    for density in (0.0, 0.1, 0.5, 1.0):
        occupancy = torch.rand(resolution, generator=generator) < density
        centres = grid.occupied_centres(occupancy)
        assert centres.shape == (int(occupancy.sum()), 3)
        torch.testing.assert_close(grid.voxelize(centres), occupancy)


def test_voxel_index_by_hand_and_upper_face():
    grid = VoxelGrid(CropBox((-1.0, 0.5, 2.0), (1.0, 2.5, 5.0)), (4, 5, 6))  # voxel size (0.5, 0.4, 0.5)
    # (0.3 + 1) / 0.5 = 2.6, (1.8 - 0.5) / 0.4 = 3.25, (4.1 - 2) / 0.5 = 4.2
    idx, inside = grid.indices(torch.tensor([[0.3, 1.8, 4.1]]))
    assert idx.tolist() == [[2, 3, 4]] and inside.tolist() == [True]
    assert grid.voxelize(torch.tensor([[0.3, 1.8, 4.1]])).nonzero().tolist() == [[2, 3, 4]]
    # The low corner is voxel (0, 0, 0); the high corner (upper faces) belongs to the last voxel.
    corners = torch.tensor([[-1.0, 0.5, 2.0], [1.0, 2.5, 5.0], [1.0, 0.6, 2.1]])
    assert grid.voxelize(corners).nonzero().tolist() == [[0, 0, 0], [3, 0, 0], [3, 4, 5]]
    # Extra columns (e.g. colours) are ignored.
    with_rgb = torch.tensor([[0.3, 1.8, 4.1, 0.9, 0.1, 0.2]])
    assert grid.voxelize(with_rgb).nonzero().tolist() == [[2, 3, 4]]


def test_points_outside_the_box_are_dropped_not_clamped():
    grid = VoxelGrid(CropBox((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)), (4, 4, 2))
    outside = torch.tensor([
        [1.001, 0.5, 0.5], [-0.001, 0.5, 0.5], [0.5, 1.2, 0.5], [0.5, -3.0, 0.5],
        [0.5, 0.5, 1.0001], [0.5, 0.5, -0.01], [2.0, 2.0, 2.0], [-5.0, -5.0, -5.0],
    ])
    assert not grid.voxelize(outside).any()
    inside = torch.tensor([[0.1, 0.1, 0.1]])
    assert grid.voxelize(torch.cat([outside, inside])).nonzero().tolist() == [[0, 0, 0]]
    _, mask = grid.indices(torch.cat([outside, inside]))
    assert mask.tolist() == [False] * 8 + [True]


def test_batched_voxelize_equals_per_cloud_voxelize():
    grid = VoxelGrid(BOX, (8, 6, 4))
    generator = torch.Generator().manual_seed(3)
    low, high = torch.tensor(BOX.low), torch.tensor(BOX.high)
    # Half the points spill outside the box on some axis.
    clouds = low - 0.25 * (high - low) + torch.rand(2, 3, 50, 3, generator=generator) * 1.5 * (high - low)
    batched = grid.voxelize(clouds)
    assert batched.shape == (2, 3, 8, 6, 4) and batched.dtype == torch.bool
    for a, b in itertools.product(range(2), range(3)):
        torch.testing.assert_close(batched[a, b], grid.voxelize(clouds[a, b]))
        # ... and per-cloud voxelize against a numpy reference.
        points = clouds[a, b].numpy().astype(np.float64)
        reference = np.zeros((8, 6, 4), dtype=bool)
        size = (np.array(BOX.high) - np.array(BOX.low)) / np.array([8, 6, 4])
        for p in points:
            if np.all(p >= BOX.low) and np.all(p <= BOX.high):
                i = np.minimum(np.floor((p - np.array(BOX.low)) / size).astype(int), [7, 5, 3])
                reference[tuple(i)] = True
        np.testing.assert_array_equal(batched[a, b].numpy(), reference)


def test_normalized_maps_voxel_centres_to_align_corners_false_coordinates():
    resolution = (5, 7, 3)
    grid = VoxelGrid(BOX, resolution)
    indices = torch.stack(torch.meshgrid(*[torch.arange(n) for n in resolution], indexing="ij"), -1).reshape(-1, 3)
    by_hand = torch.tensor([[centre_coordinate(i, n) for i, n in zip(row, resolution, strict=True)]
                            for row in indices.tolist()])
    torch.testing.assert_close(grid.normalized(grid.centres(indices)), by_hand)
    torch.testing.assert_close(normalized_centres(indices, resolution), by_hand)
    corners = torch.tensor([BOX.low, BOX.high])
    torch.testing.assert_close(grid.normalized(corners), torch.tensor([[-1.0] * 3, [1.0] * 3]))


# --------------------------------------------------------------------------------------------
# 3. IoU metrics against numpy references
# --------------------------------------------------------------------------------------------


def numpy_iou(prediction: np.ndarray, target: np.ndarray) -> float:
    predicted = set(map(tuple, np.argwhere(prediction)))
    true = set(map(tuple, np.argwhere(target)))
    union = predicted | true
    return 1.0 if not union else len(predicted & true) / len(union)


def numpy_counts(current: np.ndarray, prediction: np.ndarray, target: np.ndarray, dynamic: bool) -> np.ndarray:
    region = (target != current) | (prediction != current) if dynamic else np.ones_like(target)
    tp = np.sum(prediction & target & region)
    fp = np.sum(prediction & ~target & region)
    fn = np.sum(~prediction & target & region)
    return np.array([tp, fp, fn])


def ratio(counts: np.ndarray) -> float:
    return 1.0 if counts.sum() == 0 else counts[0] / counts.sum()


def test_voxel_iou_matches_a_numpy_set_reference():
    rng = np.random.default_rng(0)
    for density_p, density_t in [(0.1, 0.1), (0.5, 0.2), (0.02, 0.3), (0.9, 0.9)]:
        prediction = rng.random((6, 5, 4)) < density_p
        target = rng.random((6, 5, 4)) < density_t
        expected = numpy_iou(prediction, target)
        assert voxel_iou(torch.from_numpy(prediction), torch.from_numpy(target)) == pytest.approx(expected)
        acc = IoUAccumulator()
        acc.update(torch.from_numpy(target), torch.from_numpy(prediction), torch.from_numpy(target))
        assert acc.full_iou == pytest.approx(expected)


def test_iou_of_empty_grids():
    empty, some = torch.zeros(4, 4, 2, dtype=torch.bool), torch.zeros(4, 4, 2, dtype=torch.bool)
    some[1, 2, 0] = True
    assert voxel_iou(empty, empty) == 1.0
    assert voxel_iou(empty, some) == 0.0
    assert voxel_iou(some, empty) == 0.0
    assert voxel_iou(some, some) == 1.0
    assert IoUAccumulator().full_iou == 1.0 and IoUAccumulator().dynamic_iou == 1.0
    acc = IoUAccumulator()
    acc.update(some, empty, some)  # prediction empty, target not
    assert acc.full_iou == 0.0


def test_dynamic_iou_of_persistence_is_zero_and_of_a_perfect_prediction_is_one():
    rng = np.random.default_rng(1)
    for _ in range(5):
        current = rng.random((8, 8, 4)) < 0.2
        target = current.copy()
        flips = rng.random(current.shape) < 0.05
        flips[0, 0, 0] = True  # something always changes
        target ^= flips
        c, t = torch.from_numpy(current), torch.from_numpy(target)
        persistence = IoUAccumulator()
        persistence.update(c, c, t)
        assert persistence.dynamic_iou == 0.0
        assert persistence.full_iou == pytest.approx(numpy_iou(current, target))
        perfect = IoUAccumulator()
        perfect.update(c, t, t)
        assert perfect.dynamic_iou == 1.0 and perfect.full_iou == 1.0


def test_dynamic_iou_on_a_hand_built_case():
    #           voxel: 0  1  2  3  4  5  6  7
    current = [1, 0, 1, 0, 0, 0, 1, 1]
    target = [1, 0, 0, 1, 1, 0, 1, 0]
    prediction = [1, 0, 0, 1, 0, 1, 0, 1]
    # Dynamic region: voxels 2..7 (0 and 1 are static in truth and prediction).
    # There: TP = {3}, FP = {5, 7}, FN = {4, 6}. Full grid: TP = {0, 3}, FP = {5, 7}, FN = {4, 6}.
    c, t, p = (torch.tensor(g, dtype=torch.bool).reshape(2, 2, 2) for g in (current, target, prediction))
    acc = IoUAccumulator()
    acc.update(c, p, t)
    assert acc.dynamic.tolist() == [1, 2, 2]
    assert acc.full.tolist() == [2, 2, 2]
    assert acc.dynamic_iou == pytest.approx(1 / 5)
    assert acc.full_iou == pytest.approx(2 / 6)


def test_accumulation_sums_counts_instead_of_averaging_ious():
    rng = np.random.default_rng(2)
    shape = (6, 6, 3)
    samples = []
    for density in (0.02, 0.3, 0.6):
        current = rng.random(shape) < density
        target = current ^ (rng.random(shape) < 0.1)
        prediction = current ^ (rng.random(shape) < 0.1)
        samples.append((current, prediction, target))
    acc, batched = IoUAccumulator(), IoUAccumulator()
    for current, prediction, target in samples:
        acc.update(*(torch.from_numpy(g) for g in (current, prediction, target)))
    batched.update(*(torch.from_numpy(np.stack(g)) for g in zip(*samples, strict=True)))
    full = sum(numpy_counts(*s, dynamic=False) for s in samples)
    dynamic = sum(numpy_counts(*s, dynamic=True) for s in samples)
    assert acc.full.tolist() == full.tolist() and acc.dynamic.tolist() == dynamic.tolist()
    assert batched.full.tolist() == full.tolist() and batched.dynamic.tolist() == dynamic.tolist()
    assert acc.full_iou == pytest.approx(ratio(full))
    assert acc.dynamic_iou == pytest.approx(ratio(dynamic))
    mean_of_ious = np.mean([numpy_iou(p, t) for _, p, t in samples])
    assert abs(acc.full_iou - mean_of_ious) > 1e-3, "the test case must tell summing from averaging"
    # The plain count helper, by hand.
    assert iou_from_counts(torch.tensor([3, 1, 2])) == pytest.approx(0.5)
    assert iou_from_counts(torch.tensor([0, 0, 0])) == 1.0


# --------------------------------------------------------------------------------------------
# 4. focal loss
# --------------------------------------------------------------------------------------------


def focal_by_hand(logits: torch.Tensor, labels: torch.Tensor, alpha: float | None, gamma: float) -> torch.Tensor:
    p = torch.sigmoid(logits)
    p_t = torch.where(labels > 0.5, p, 1 - p)
    weight = 1.0 if alpha is None else torch.where(labels > 0.5, alpha, 1 - alpha)
    return (-weight * (1 - p_t) ** gamma * torch.log(p_t)).mean()


@pytest.mark.parametrize("alpha", [None, 0.25, 0.8])
@pytest.mark.parametrize("gamma", [0.0, 1.0, 2.0, 3.5])
def test_focal_loss_matches_the_formula(alpha, gamma):
    generator = torch.Generator().manual_seed(0)
    logits = torch.randn(200, generator=generator, dtype=torch.float64) * 4
    labels = (torch.rand(200, generator=generator) < 0.4).double()
    torch.testing.assert_close(focal_loss(logits, labels, alpha=alpha, gamma=gamma),
                               focal_by_hand(logits, labels, alpha, gamma))


def test_focal_loss_with_gamma_zero_is_binary_cross_entropy():
    generator = torch.Generator().manual_seed(1)
    logits = torch.randn(3, 50, generator=generator, dtype=torch.float64) * 3
    labels = (torch.rand(3, 50, generator=generator) < 0.5).double()
    p = torch.sigmoid(logits)
    bce = -(labels * torch.log(p) + (1 - labels) * torch.log(1 - p)).mean()
    torch.testing.assert_close(focal_loss(logits, labels, alpha=None, gamma=0.0), bce)
    # With alpha, positives weigh alpha and negatives 1 - alpha.
    weighted = -(0.3 * labels * torch.log(p) + 0.7 * (1 - labels) * torch.log(1 - p)).mean()
    torch.testing.assert_close(focal_loss(logits, labels, alpha=0.3, gamma=0.0), weighted)


def test_focal_loss_is_stable_for_large_logits():
    logits = torch.tensor([100.0, -100.0, 100.0, -100.0], requires_grad=True)
    labels = torch.tensor([1.0, 0.0, 0.0, 1.0])
    loss = focal_loss(logits, labels, alpha=None, gamma=2.0)
    # Two confident right answers cost 0; two confident wrong ones cost -log(sigmoid(-100)) = 100 each.
    assert torch.isfinite(loss) and loss.item() == pytest.approx(50.0, rel=1e-4)
    loss.backward()
    assert torch.isfinite(logits.grad).all()
    for alpha in (None, 0.25):
        for gamma in (0.0, 2.0):
            value = focal_loss(logits.detach(), labels, alpha=alpha, gamma=gamma)
            assert torch.isfinite(value)


# --------------------------------------------------------------------------------------------
# 5. near band and balanced queries
# --------------------------------------------------------------------------------------------


def near_band_brute_force(occupancy: np.ndarray, distance: int) -> np.ndarray:
    """For every voxel, is the Chebyshev distance to the nearest occupied voxel <= distance?"""
    result = np.zeros_like(occupancy)
    for b in range(occupancy.shape[0]):
        occupied = np.argwhere(occupancy[b])
        for index in itertools.product(*(range(n) for n in occupancy.shape[1:])):
            if len(occupied):
                result[(b, *index)] = np.abs(occupied - np.array(index)).max(axis=1).min() <= distance
    return result


@pytest.mark.parametrize("distance", [0, 1, 2, 6])  # 6: beyond every axis of the grid
def test_near_band_matches_brute_force_chebyshev(distance):
    rng = np.random.default_rng(distance)
    occupancy = rng.random((3, 7, 6, 5)) < 0.03
    occupancy[0, 0, 0, 0] = True  # a corner voxel
    occupancy[1, 6, 2, 4] = True  # on a face
    occupancy[2] = False  # an empty sample
    band = near_band(torch.from_numpy(occupancy), distance)
    assert band.shape == occupancy.shape and band.dtype == torch.bool
    np.testing.assert_array_equal(band.numpy(), near_band_brute_force(occupancy, distance))


def categories_by_hand(target: np.ndarray, distance: int) -> np.ndarray:
    """0 = occupied, 1 = free within ``distance`` of an occupied voxel, 2 = far free."""
    band = near_band_brute_force(target, distance)
    return np.where(target, 0, np.where(band, 1, 2))


def check_queries(target: torch.Tensor, indices: torch.Tensor, labels: torch.Tensor, n_queries: int) -> None:
    batch = target.shape[0]
    assert indices.shape == (batch, n_queries, 3) and labels.shape == (batch, n_queries)
    for axis, n in enumerate(target.shape[1:]):
        assert indices[..., axis].min() >= 0 and indices[..., axis].max() < n
    for b in range(batch):
        i, j, k = indices[b].unbind(-1)
        torch.testing.assert_close(labels[b], target[b, i, j, k].float())


def category_counts(target: np.ndarray, indices: torch.Tensor, distance: int) -> list[list[int]]:
    categories = categories_by_hand(target, distance)
    counts = []
    for b in range(target.shape[0]):
        found = categories[b][tuple(indices[b].numpy().T)]
        counts.append([int((found == c).sum()) for c in range(3)])
    return counts


def test_balanced_queries_draw_a_third_from_each_category():
    rng = np.random.default_rng(5)
    target = np.zeros((2, 10, 9, 6), dtype=bool)
    target[0, 4:6, 3:5, 2:4] = True
    target[1] = rng.random((10, 9, 6)) < 0.02
    target[1, 0, 0, 0] = True
    generator = torch.Generator().manual_seed(0)
    for n_queries in (300, 301, 302):
        indices, labels = balanced_queries(torch.from_numpy(target), n_queries, 1, generator)
        check_queries(torch.from_numpy(target), indices, labels, n_queries)
        share, extra = divmod(n_queries, 3)
        expected = sorted([share + 1] * extra + [share] * (3 - extra))
        for counts in category_counts(target, indices, 1):
            assert sorted(counts) == expected


def test_balanced_queries_give_an_empty_category_share_to_the_others():
    generator = torch.Generator().manual_seed(1)
    # An empty target: only far free voxels exist.
    empty = torch.zeros(1, 5, 5, 4, dtype=torch.bool)
    indices, labels = balanced_queries(empty, 90, 2, generator)
    check_queries(empty, indices, labels, 90)
    assert not labels.any()
    # near_distance = 0: the near band is the occupied set itself, so no near free voxel exists.
    target = np.zeros((1, 6, 6, 4), dtype=bool)
    target[0, 2, 3, 1] = target[0, 4, 4, 2] = True
    indices, labels = balanced_queries(torch.from_numpy(target), 90, 0, generator)
    check_queries(torch.from_numpy(target), indices, labels, 90)
    assert category_counts(target, indices, 0) == [[45, 0, 45]]
    # A band that covers the whole grid: no far voxel, half occupied and half near.
    target = np.zeros((1, 4, 4, 3), dtype=bool)
    target[0, 1, 2, 1] = True
    indices, labels = balanced_queries(torch.from_numpy(target), 91, 3, generator)
    check_queries(torch.from_numpy(target), indices, labels, 91)
    assert sorted(category_counts(target, indices, 3)[0]) == [0, 45, 46]
    assert category_counts(target, indices, 3)[0][2] == 0
    # A full grid: every query is occupied.
    full = torch.ones(1, 3, 3, 2, dtype=torch.bool)
    indices, labels = balanced_queries(full, 20, 1, generator)
    check_queries(full, indices, labels, 20)
    assert labels.all()


def test_balanced_queries_are_reproducible_with_a_seeded_generator():
    target = torch.rand(2, 8, 8, 4, generator=torch.Generator().manual_seed(9)) < 0.05
    first = balanced_queries(target, 128, 2, torch.Generator().manual_seed(42))
    again = balanced_queries(target, 128, 2, torch.Generator().manual_seed(42))
    other = balanced_queries(target, 128, 2, torch.Generator().manual_seed(43))
    assert torch.equal(first[0], again[0]) and torch.equal(first[1], again[1])
    assert not torch.equal(first[0], other[0])


# --------------------------------------------------------------------------------------------
# 6. positional embedding
# --------------------------------------------------------------------------------------------


def test_positional_embedding_shape_and_values():
    assert positional_embedding(torch.zeros(2, 5, 3), 6).shape == (2, 5, 3 + 36)
    embedding = positional_embedding(torch.tensor([0.5, -0.25, 1.0]), 2)
    r = math.sqrt(0.5)
    # [x, y, z, sin(pi x), sin(2 pi x), sin(pi y), sin(2 pi y), sin(pi z), sin(2 pi z), the same with cos]
    expected = [0.5, -0.25, 1.0,
                1.0, 0.0, -r, -1.0, 0.0, 0.0,
                0.0, -1.0, r, 0.0, -1.0, 1.0]
    torch.testing.assert_close(embedding, torch.tensor(expected), atol=1e-6, rtol=0)
    # The set of values does not depend on the layout chosen.
    assert sorted(embedding.tolist()) == pytest.approx(sorted(expected), abs=1e-6)


# --------------------------------------------------------------------------------------------
# 7. The model: shapes, zero-initialised FiLM, predict_grid, and overfitting one real transition
# --------------------------------------------------------------------------------------------

SMALL_MODEL = dict(resolution=(12, 10, 6), channels=8, refine_dilations=(1, 2), pe_frequencies=3,
                   decoder_hidden=32, action_history=3, action_dim=4)


@pytest.mark.parametrize("skip", [True, False])
@pytest.mark.parametrize("mode", FEATURE_MODES)
def test_feature_modes_build_give_logits_and_film_starts_at_zero(mode, skip):
    torch.manual_seed(0)
    config = WorldModelConfig(feature_mode=mode, occupancy_skip=skip, **SMALL_MODEL)
    model = TriplaneWorldModel(config)
    generator = torch.Generator().manual_seed(0)
    occupancy = torch.rand(2, *config.resolution, generator=generator) < 0.1
    queries = torch.rand(2, 17, 3, generator=generator) * 2 - 1
    actions = torch.randn(2, 3, 4, generator=generator)
    logits = model(occupancy, actions, queries)
    assert logits.shape == (2, 17) and torch.isfinite(logits).all()
    features = model.encode(occupancy, actions)
    C = config.channels
    X, Y, Z = config.resolution
    expected_shapes = {"triplane": [(2, C, X, Y), (2, C, X, Z), (2, C, Y, Z)], "xy": [(2, C, X, Y)],
                       "volume": [(2, C, X, Y, Z)]}[mode] + [(2, 1, X, Y, Z)] * skip
    assert [tuple(f.shape) for f in features] == expected_shapes
    # Freshly initialised: the action history changes nothing.
    torch.testing.assert_close(model(occupancy, torch.zeros_like(actions), queries), logits, rtol=0, atol=0)
    torch.testing.assert_close(model(occupancy, 10 * actions, queries), logits, rtol=0, atol=0)
    # ... but actions do reach the features once FiLM is non-zero (the check above is not vacuous).
    with torch.no_grad():
        model.film[-1].bias.normal_(generator=generator)
        model.film[-1].weight.normal_(generator=generator)
    assert not torch.allclose(model(occupancy, torch.zeros_like(actions), queries), model(occupancy, actions, queries))
    # The occupancy does matter.
    assert not torch.allclose(model(~occupancy, actions, queries), model(occupancy, actions, queries))


@pytest.mark.parametrize("encoder", ["volume-conv", "point-scatter"])
def test_a_model_that_reads_no_actions_imagines_the_same_whatever_they_were(encoder):
    """With ``reads_actions=False`` a trained (non-zero) FiLM still gives one output for any
    action history: the one a model that read zeros would give."""
    config = WorldModelConfig(feature_mode="triplane", encoder=encoder, reads_actions=False, **SMALL_MODEL)
    model = TriplaneWorldModel(config)
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        model.film[-1].bias.normal_(generator=generator)
        model.film[-1].weight.normal_(generator=generator)
    reading = TriplaneWorldModel(dataclasses.replace(config, reads_actions=True))
    reading.load_state_dict(model.state_dict())
    occupancy = torch.rand(2, *config.resolution, generator=generator) < 0.1
    queries = torch.rand(2, 9, 3, generator=generator) * 2 - 1
    actions = torch.randn(2, 3, 4, generator=generator)
    still = reading(occupancy, torch.zeros_like(actions), queries)
    assert not torch.allclose(reading(occupancy, actions, queries), still)  # the weights do read actions
    for history in (actions, -5 * actions):
        torch.testing.assert_close(model(occupancy, history, queries), still, rtol=0, atol=0)
    assert WorldModelConfig.from_dict({k: v for k, v in config.to_dict().items() if k != "reads_actions"}).reads_actions


class FixedVolume(nn.Module):
    """Stands in for the encoder: returns a given feature volume whatever the occupancy."""

    def __init__(self, volume: torch.Tensor) -> None:
        super().__init__()
        self.volume = volume

    def forward(self, occupancy: torch.Tensor) -> torch.Tensor:
        return self.volume


@pytest.mark.parametrize("pooling", ["mean", "max"])
@pytest.mark.parametrize("skip", [True, False])
@pytest.mark.parametrize("mode", FEATURE_MODES)
def test_planes_pool_the_right_axes_and_queries_read_the_right_planes(mode, skip, pooling):
    """With a known feature volume and identity refiners, the planes are the axis means or
    maxima (xy: over z, xz: over y, yz: over x) and a query at the centre of voxel (i, j, k) reads
    P_xy[i, j] + P_xz[i, k] + P_yz[j, k] (triplane), P_xy[i, j] (xy) or V[i, j, k] (volume);
    with ``occupancy_skip`` the decoder also gets the current occupancy of that voxel."""
    config = WorldModelConfig(feature_mode=mode, occupancy_skip=skip, plane_pooling=pooling, **SMALL_MODEL)
    model = TriplaneWorldModel(config)
    X, Y, Z = config.resolution
    generator = torch.Generator().manual_seed(4)
    volume = torch.randn(1, config.channels, X, Y, Z, generator=generator)
    occupancy = torch.rand(1, X, Y, Z, generator=generator) < 0.3
    model.encoder = FixedVolume(volume)
    model.refine = nn.ModuleList([nn.Identity() for _ in model.refine])
    features = model.encode(occupancy, torch.zeros(1, 3, 4))
    v = volume[0].numpy()
    pool = np.mean if pooling == "mean" else np.max
    expected_planes = {"triplane": [pool(v, axis=3), pool(v, axis=2), pool(v, axis=1)], "xy": [pool(v, axis=3)],
                       "volume": [v]}[mode]
    assert len(features) == len(expected_planes) + int(skip)
    for got, want in zip(features, expected_planes, strict=False):
        np.testing.assert_allclose(got[0].detach().numpy(), want, rtol=1e-5, atol=1e-6)
    cells = [(0, 0, 0), (11, 9, 5), (3, 7, 1), (6, 2, 4), (10, 0, 5), *map(tuple, occupancy[0].nonzero()[:5].tolist())]
    queries = torch.tensor([[centre_coordinate(i, X), centre_coordinate(j, Y), centre_coordinate(k, Z)]
                            for i, j, k in cells])[None]
    sampled = model.query_features(features, queries)[0].detach().numpy()
    decoder_inputs = []
    model.decoder.register_forward_pre_hook(lambda module, args: decoder_inputs.append(args[0].detach()))
    model.decode(features, queries)
    (inputs,) = decoder_inputs
    C, width = config.channels, 3 + 6 * config.pe_frequencies
    assert inputs.shape == (1, len(cells), C + width + int(skip))
    for q, (i, j, k) in enumerate(cells):
        if mode == "triplane":
            want = pool(v[:, i, j, :], -1) + pool(v[:, i, :, k], -1) + pool(v[:, :, j, k], -1)
        elif mode == "xy":
            want = pool(v[:, i, j, :], -1)
        else:
            want = v[:, i, j, k]
        np.testing.assert_allclose(sampled[q], want, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(inputs[0, q, :C].numpy(), want, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(inputs[0, q, C:C + 3].numpy(), queries[0, q].numpy())
        if skip:
            assert inputs[0, q, -1].item() == pytest.approx(float(occupancy[0, i, j, k]), abs=1e-6)


def test_world_model_config_rejects_bad_values():
    with pytest.raises(ValueError, match="feature_mode"):
        WorldModelConfig(feature_mode="planes")
    with pytest.raises(ValueError, match="plane_pooling"):
        WorldModelConfig(plane_pooling="sum")
    with pytest.raises(ValueError, match="horizon"):
        WorldModelConfig(horizon=0)


def test_predict_grid_decodes_every_voxel_centre_in_c_order():
    torch.manual_seed(1)
    config = WorldModelConfig(feature_mode="triplane", **SMALL_MODEL)
    model = TriplaneWorldModel(config).eval()
    generator = torch.Generator().manual_seed(1)
    current = torch.rand(2, *config.resolution, generator=generator) < 0.1
    actions = torch.randn(2, 3, 4, generator=generator)
    X, Y, Z = config.resolution
    cells = list(itertools.product(range(X), range(Y), range(Z)))
    queries = torch.tensor([[centre_coordinate(i, X), centre_coordinate(j, Y), centre_coordinate(k, Z)]
                            for i, j, k in cells])
    with torch.no_grad():
        logits = model(current, actions, queries.expand(2, -1, -1))
    for threshold in (0.5, 0.3):
        expected = (torch.sigmoid(logits) > threshold).reshape(2, X, Y, Z)
        cut = math.log(threshold / (1 - threshold))
        ambiguous = (logits - cut).abs() < 1e-5  # float round-off right at the threshold
        for chunk in (7, 1 << 16):
            grid = predict_grid(model, current, actions, threshold=threshold, chunk=chunk)
            assert grid.shape == (2, X, Y, Z) and grid.dtype == torch.bool
            assert torch.equal(grid[~ambiguous.reshape(2, X, Y, Z)], expected[~ambiguous.reshape(2, X, Y, Z)])


class KnownFuture(nn.Module):
    """Stands in for the world model: logit +10 inside the given future voxels, -10 elsewhere."""

    def __init__(self, future: torch.Tensor) -> None:
        super().__init__()
        self.future = future
        self.config = WorldModelConfig(resolution=tuple(future.shape), action_history=1, action_dim=4)

    def encode(self, occupancy: torch.Tensor, actions: torch.Tensor) -> list[torch.Tensor]:
        return []

    def decode(self, features: list[torch.Tensor], queries: torch.Tensor) -> torch.Tensor:
        resolution = torch.tensor(self.future.shape)
        index = ((queries + 1) / 2 * resolution).floor().long()
        return torch.where(self.future[tuple(index.unbind(-1))], 10.0, -10.0)

    def voxel_decoder(self, features: list[torch.Tensor]):
        return lambda indices: torch.where(self.future[tuple(indices.T)], 10.0, -10.0)


@pytest.mark.parametrize("keep_observed_points", [False, True])
def test_imaginer_decodes_the_imagined_voxels_keeping_observed_points_if_asked(keep_observed_points):
    """Grid of 4 x 4 x 2 voxels of 0.25 m over [0, 1] x [0, 1] x [0, 0.5]. The current cloud
    fills voxels A = (0, 0, 0) and B = (3, 3, 1); the model keeps A and replaces B by the
    empty voxel C = (1, 0, 0). Expected: A's observed points (or A's centre) and C's centre
    (0.375, 0.125, 0.125); nothing in B."""
    grid = VoxelGrid(CropBox((0.0, 0.0, 0.0), (1.0, 1.0, 0.5)), (4, 4, 2))
    in_a = torch.tensor([[0.02, 0.03, 0.01], [0.2, 0.1, 0.24], [0.11, 0.22, 0.05]])
    in_b = torch.tensor([[0.9, 0.8, 0.4], [0.95, 0.99, 0.3]])
    future = torch.zeros(4, 4, 2, dtype=torch.bool)
    future[0, 0, 0] = future[1, 0, 0] = True
    centre_a, centre_c = [0.125, 0.125, 0.125], [0.375, 0.125, 0.125]
    expected = [*in_a.tolist(), centre_c] if keep_observed_points else [centre_a, centre_c]
    imaginer = Imaginer(KnownFuture(future), grid, num_points=len(expected), keep_observed_points=keep_observed_points)
    imagined = imaginer(torch.cat([in_a, in_b]), torch.zeros(1, 4))
    assert imagined.shape == (len(expected), 3)
    np.testing.assert_allclose(sorted(imagined.tolist()), sorted(expected), atol=1e-6)


def test_imaginer_change_output_holds_the_voxels_it_fills_that_are_empty_now():
    """The scene above: A stays, B empties, C fills. The change cloud is C's centre alone;
    where the model fills nothing new, the likeliest empty decoded voxels stand in."""
    grid = VoxelGrid(CropBox((0.0, 0.0, 0.0), (1.0, 1.0, 0.5)), (4, 4, 2))
    cloud = torch.tensor([[0.02, 0.03, 0.01], [0.2, 0.1, 0.24], [0.9, 0.8, 0.4], [0.95, 0.99, 0.3]])
    future = torch.zeros(4, 4, 2, dtype=torch.bool)
    future[0, 0, 0] = future[1, 0, 0] = True
    imaginer = Imaginer(KnownFuture(future), grid, num_points=3, output="change")
    np.testing.assert_allclose(imaginer(cloud, torch.zeros(1, 4)), [[0.375, 0.125, 0.125]] * 3, atol=1e-6)
    # Nothing new: every decoded voxel holds logit -10 except A (kept, +10, but occupied now).
    still = torch.zeros(4, 4, 2, dtype=torch.bool)
    still[0, 0, 0] = True
    imagined = Imaginer(KnownFuture(still), grid, num_points=5, output="change")(cloud, torch.zeros(1, 4))
    assert imagined.shape == (5, 3)
    occupied_now = {(0, 0, 0), (3, 3, 1)}
    voxels = {tuple(index) for index in grid.indices(torch.as_tensor(imagined))[0].tolist()}
    assert voxels and not voxels & occupied_now  # only voxels empty now, all near the present
    with pytest.raises(ValueError, match="output must be one of"):
        Imaginer(KnownFuture(still), grid, num_points=5, output="past")


class GradedFuture(KnownFuture):
    """KnownFuture with a logit per voxel: the likeliest voxels are known."""

    def __init__(self, logits: torch.Tensor) -> None:
        super().__init__(logits > 0)
        self.logits = logits

    def voxel_decoder(self, features: list[torch.Tensor]):
        return lambda indices: self.logits[tuple(indices.T)]


def test_imaginer_change_top_keeps_the_likeliest_filled_voxels():
    """A 4 x 1 x 1 row: A = voxel 0 occupied now; the model fills 1, 2, 3 with logits 1, 5, 3.
    With 2 points: change-top keeps voxels 2 and 3 (the likeliest), change samples all three apart."""
    grid = VoxelGrid(CropBox((0.0, 0.0, 0.0), (4.0, 1.0, 1.0)), (4, 1, 1))
    logits = torch.tensor([10.0, 1.0, 5.0, 3.0]).reshape(4, 1, 1)
    cloud = torch.tensor([[0.5, 0.5, 0.5]])
    top = Imaginer(GradedFuture(logits), grid, num_points=2, band=3, output="change-top")(cloud, torch.zeros(1, 4))
    assert sorted(top[:, 0].tolist()) == [2.5, 3.5]
    spread = Imaginer(GradedFuture(logits), grid, num_points=2, band=3, output="change")(cloud, torch.zeros(1, 4))
    assert 1.5 in spread[:, 0].tolist()  # farthest-point sampling starts from the first filled voxel
    # With more points than filled voxels, change-top holds every filled one.
    every = Imaginer(GradedFuture(logits), grid, num_points=5, band=3, output="change-top")(cloud, torch.zeros(1, 4))
    assert set(every[:, 0].tolist()) == {1.5, 2.5, 3.5}


@pytest.mark.parametrize("mode, encoder, skip", [
    ("triplane", "point-scatter", True), ("xy", "point-scatter", True), ("triplane", "volume-conv", False),
    ("volume", "volume-conv", True),
])
@pytest.mark.parametrize("chunk", [4096, 48])
def test_voxel_decoder_equals_the_generic_decoder_at_voxel_centres(mode, encoder, skip, chunk, monkeypatch):
    """The table decoder (first layer split per plane cell and axis) against decode(): bilinear
    plane sampling, the full positional embedding and the whole MLP at every voxel centre, with
    random weights large enough that every term matters; in one chunk and in chunks of 48."""
    monkeypatch.setattr(VoxelDecoder, "CHUNK", chunk)
    torch.manual_seed(0)
    config = WorldModelConfig(resolution=(10, 8, 4), channels=8, feature_mode=mode, encoder=encoder,
                              occupancy_skip=skip, pe_frequencies=3)
    model = TriplaneWorldModel(config)
    for parameter in model.parameters():
        nn.init.normal_(parameter, std=0.3)
    occupancy = torch.rand(1, *config.resolution) < 0.2
    with torch.no_grad():
        features = model.encode(occupancy, torch.randn(1, config.action_history, config.action_dim))
        indices = torch.stack(torch.meshgrid(*[torch.arange(n) for n in config.resolution], indexing="ij"), -1)
        indices = indices.reshape(-1, 3)[torch.randperm(10 * 8 * 4)]
        expected = model.decode(features, normalized_centres(indices, config.resolution)[None])[0]
        actual = model.voxel_decoder(features)(indices)
    assert expected.abs().max() > 1.0
    torch.testing.assert_close(actual, expected, atol=1e-4, rtol=1e-4)


def test_voxel_decoder_refuses_a_batch():
    model = TriplaneWorldModel(WorldModelConfig(resolution=(4, 4, 2), channels=4))
    features = model.encode(torch.zeros(2, 4, 4, 2, dtype=torch.bool), torch.zeros(2, 4, 4))
    with pytest.raises(ValueError, match="one scene"):
        model.voxel_decoder(features)


def _bar(x_voxels: range) -> torch.Tensor:
    grid = torch.zeros(12, 3, 2, dtype=torch.bool)
    grid[list(x_voxels), 1, 0] = True
    return grid


@pytest.mark.parametrize("future_x, band, grow, reached", [
    (range(2, 7), 4, True, range(2, 7)),    # the bar grows 3 voxels: followed ring by ring
    (range(2, 7), 4, False, range(2, 7)),   # the whole band finds it too
    (range(2, 7), 2, True, range(2, 6)),    # but no farther than the band
    (range(2, 7), 1, True, range(2, 5)),
    (range(6, 8), 4, False, range(6, 8)),    # a jump over 2 empty voxels: only the whole band sees it
    (range(6, 8), 4, True, range(0)),        # growing needs a path of filled voxels from the present
])
def test_imaginer_decodes_within_the_band_growing_from_what_the_model_fills(future_x, band, grow, reached):
    """A 12-voxel row holds a bar at x = 2, 3 now; the stand-in model knows the future bar."""
    grid = VoxelGrid(CropBox((0.0, 0.0, 0.0), (1.2, 0.3, 0.2)), (12, 3, 2))
    current = _bar(range(2, 4))[None]
    imaginer = Imaginer(KnownFuture(_bar(future_x)), grid, num_points=8, band=band, grow=grow)
    indices, logits = imaginer.decoded_voxels(current, [])
    occupied = sorted(indices[logits > 0][:, 0].tolist())
    assert occupied == list(reached)
    assert len(indices) == len({tuple(index) for index in indices.tolist()}), "a voxel decoded twice"


@pytest.fixture(scope="module")
def real_transition() -> tuple[torch.Tensor, torch.Tensor, np.ndarray]:
    """Voxelised clouds of Reach at reset and after 4 steps of a constant action."""
    env = gym.make("D2A-MetaWorld-Reach-v0", image_size=48, num_points=256)
    observation, _ = env.reset(seed=0)
    before = observation["point_cloud"]
    action = np.array([1.0, 0.0, 0.0, 0.0], dtype=np.float32)
    for _ in range(4):
        observation, *_ = env.step(action)
    after = observation["point_cloud"]
    env.close()
    grid = VoxelGrid(d2a_envs.SUITE_DEFAULTS["metaworld"].crop_box, (32, 32, 8))
    current, target = grid.voxelize(torch.as_tensor(before)), grid.voxelize(torch.as_tensor(after))
    assert current.any() and target.any() and not torch.equal(current, target)
    return current[None], target[None], action


@pytest.mark.parametrize("skip", [True, False])
def test_model_overfits_one_real_transition(real_transition, skip):
    current, target, action = real_transition
    config = WorldModelConfig(resolution=(32, 32, 8), channels=8, refine_dilations=(1, 2), pe_frequencies=4,
                              decoder_hidden=64, horizon=4, action_history=4, action_dim=4, occupancy_skip=skip)
    resolution = torch.tensor(config.resolution, dtype=torch.float32)
    actions = torch.as_tensor(action).repeat(1, 4, 1)
    persistence = voxel_iou(current, target)
    assert persistence < 0.9, "the transition must move enough to be a real test"
    best = 0.0
    with single_thread():
        torch.manual_seed(0)
        model = TriplaneWorldModel(config)
        optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
        generator = torch.Generator().manual_seed(0)
        for step in range(1, 401):
            indices, labels = balanced_queries(target, 1024, 2, generator)
            queries = (indices.float() + 0.5) / resolution * 2.0 - 1.0
            loss = focal_loss(model(current, actions, queries), labels, alpha=None)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            if step >= 100 and step % 25 == 0:
                model.eval()
                best = voxel_iou(predict_grid(model, current, actions), target)
                model.train()
                if best > 0.95:
                    break
    assert best > 0.95, f"full-grid IoU {best:.3f} after {step} steps (persistence {persistence:.3f})"


# --------------------------------------------------------------------------------------------
# 8. WorldModelTransitions
# --------------------------------------------------------------------------------------------

# Row r's cloud is two points in voxel (r, 0, 0) of a 1-D grid of 8 voxels, so the voxelised
# target tells which row it came from; row r's action is (r + 1, -10 (r + 1)), never zero.
LINE_GRID = VoxelGrid(CropBox((0.0, 0.0, 0.0), (8.0, 1.0, 1.0)), (8, 1, 1))
EPISODES = [5, 5, 5, 5, 5, 9, 9, 9]  # two episodes: rows 0-4 and rows 5-7


def line_frames() -> TensorDict:
    rows = torch.arange(len(EPISODES), dtype=torch.float32)
    clouds = torch.stack([torch.tensor([[r + 0.3, 0.5, 0.5], [r + 0.7, 0.2, 0.8]]) for r in rows.tolist()])
    actions = torch.stack([rows + 1, -10 * (rows + 1)], dim=-1)
    return TensorDict({"point_cloud": clouds, "action": actions, "episode": torch.tensor(EPISODES)},
                      batch_size=[len(EPISODES)])


def expected_transitions(horizon: int, history: int, episodes=(5, 9)):
    """(row, target row, K x 2 actions) by hand, from the episode layout alone."""
    out = []
    for episode in episodes:
        rows = [r for r, e in enumerate(EPISODES) if e == episode]
        start, last = rows[0], rows[-1]
        for row in rows:
            past = [row - k for k in range(history, 0, -1)]  # a_{t-K} .. a_{t-1}
            acts = [[p + 1.0, -10.0 * (p + 1)] if p >= start else [0.0, 0.0] for p in past]
            out.append((row, min(row + horizon, last), acts))
    return out


def row_of(grid: torch.Tensor) -> int:
    occupied = grid.nonzero()
    assert len(occupied) == 1
    return int(occupied[0, 0])


@pytest.mark.parametrize(("horizon", "history"), [(2, 3), (1, 1), (6, 2)])
def test_transitions_target_and_action_history(horizon, history):
    transitions = WorldModelTransitions(line_frames(), LINE_GRID, horizon=horizon, action_history=history)
    expected = expected_transitions(horizon, history)
    assert len(transitions) == len(expected) == 8
    batch = transitions.get(torch.arange(len(transitions)))
    assert batch.current.shape == (8, 8, 1, 1) and batch.target.shape == (8, 8, 1, 1)
    assert batch.actions.shape == (8, history, 2) and batch.actions.dtype == torch.float32
    for i, (row, target_row, acts) in enumerate(expected):
        assert row_of(batch.current[i]) == row
        assert row_of(batch.target[i]) == target_row
        assert batch.actions[i].tolist() == acts, f"row {row}"


def test_transitions_of_selected_episodes_and_sampling():
    transitions = WorldModelTransitions(line_frames(), LINE_GRID, horizon=2, action_history=3, episodes=[9])
    assert len(transitions) == 3
    batch = transitions.get(torch.arange(3))
    for i, (row, target_row, acts) in enumerate(expected_transitions(2, 3, episodes=(9,))):
        assert row_of(batch.current[i]) == row and row_of(batch.target[i]) == target_row
        assert batch.actions[i].tolist() == acts
    # The first step of episode 9 sees only zeros, never episode 5's last actions.
    assert batch.actions[0].abs().sum() == 0
    sample = transitions.sample(16, torch.Generator().manual_seed(0))
    assert sample.current.shape == (16, 8, 1, 1)
    assert {row_of(g) for g in sample.current} <= {5, 6, 7}
    with pytest.raises(ValueError, match="unknown episode"):
        WorldModelTransitions(line_frames(), LINE_GRID, horizon=2, action_history=3, episodes=[7])


# --- the point-scatter encoder ---------------------------------------------------------


def test_point_scatter_planes_equal_max_pooling_a_dense_feature_volume():
    """The scatter route against the dense one it replaces: a volume holding each occupied
    voxel's features (0 elsewhere), max-pooled along each axis."""
    torch.manual_seed(0)
    resolution = (6, 5, 4)
    config = WorldModelConfig(resolution=resolution, channels=4, encoder="point-scatter", refine_dilations=(1,))
    model = TriplaneWorldModel(config)
    torch.nn.init.normal_(model.film[-1].weight)  # a non-trivial FiLM
    occupancy = torch.rand(2, *resolution) < 0.2
    actions = torch.randn(2, config.action_history, config.action_dim)
    gamma, beta = model.film(actions.flatten(1)).chunk(2, dim=-1)
    planes = model._scatter_planes(occupancy, gamma, beta)

    volume = torch.zeros(2, config.channels, *resolution)
    for b, x, y, z in itertools.product(range(2), *(range(n) for n in resolution)):
        if occupancy[b, x, y, z]:
            centre = (torch.tensor([x, y, z]) + 0.5) / torch.tensor(resolution) * 2 - 1
            volume[b, :, x, y, z] = torch.relu(model.encoder(centre) * (1 + gamma[b]) + beta[b])
    for plane, axis in zip(planes, (4, 3, 2), strict=True):
        torch.testing.assert_close(plane, volume.amax(dim=axis))


def test_point_scatter_model_trains_and_serves_xy_but_not_volume():
    config = WorldModelConfig(resolution=(8, 8, 4), channels=4, encoder="point-scatter", refine_dilations=(1,))
    model = TriplaneWorldModel(config)
    occupancy = torch.rand(2, 8, 8, 4) < 0.1
    logits = model(occupancy, torch.randn(2, config.action_history, 4), torch.rand(2, 16, 3) * 2 - 1)
    logits.sum().backward()
    assert logits.shape == (2, 16) and model.encoder[0].weight.grad is not None
    xy = TriplaneWorldModel(WorldModelConfig(resolution=(8, 8, 4), channels=4, encoder="point-scatter",
                                             feature_mode="xy", refine_dilations=(1,)))
    assert len(xy.encode(occupancy, torch.zeros(2, 4, 4))) == 2  # the xy plane and the occupancy skip
    with pytest.raises(ValueError, match="point-scatter encoder builds planes"):
        WorldModelConfig(encoder="point-scatter", feature_mode="volume")
    with pytest.raises(ValueError, match="encoder must be one of"):
        WorldModelConfig(encoder="sparse")


def test_world_model_split_on_the_first_demonstrations():
    from types import SimpleNamespace

    from d2a_agents.world_model.train import split_episodes

    episodes = [SimpleNamespace(index=i, task="push") for i in range(10)]
    dataset = SimpleNamespace(metadata=SimpleNamespace(tasks={"push": {}}, episodes=episodes), directory="d")
    assert split_episodes(dataset, 0.2) == (list(range(8)), [8, 9])
    assert split_episodes(dataset, 0.2, demos=10) == (list(range(8)), [8, 9])  # all of them: as before
    assert split_episodes(dataset, 0.2, demos=5) == ([0, 1, 2, 3, 4], [5])  # validated on the next one
    assert split_episodes(dataset, 0.2, demos=1) == ([0], [1])
    with pytest.raises(ValueError, match="fewer than demos=11"):
        split_episodes(dataset, 0.2, demos=11)
