"""The point-budget bench: its two measures against hand-built clouds, then on Hand-Insert's two boxes."""

from __future__ import annotations

import numpy as np

from benchmarks.point_budget import PointBudgetConfig, densest_band_share, measure_task, points_near

OLD_BOX = ((-0.6, 0.25, 0.005), (0.6, 0.97, 0.7))  # Meta-World's box, floor 5 mm above z = 0


def test_densest_band_share_counts_the_flattest_slice():
    rng = np.random.default_rng(0)
    table = np.column_stack([rng.uniform(-1, 1, (80, 2)), np.full(80, 0.0502)])  # one slice, 5.0-5.5 cm
    above = np.column_stack([rng.uniform(-1, 1, (20, 2)), 0.1 + 0.05 * np.arange(20)])  # 5 cm apart
    cloud = np.vstack([above, table])
    assert densest_band_share(cloud) == 0.8
    assert densest_band_share(above) == 0.05


def test_points_near_counts_within_the_radius():
    cloud = np.array([[0.0, 0.0, 0.0], [0.03, 0.0, 0.0], [0.0, 0.05, 0.0], [0.02, 0.02, 0.02]])
    assert points_near(cloud, np.zeros(3)) == 3  # 0, 3 and 3.5 cm; 5 cm is out
    assert points_near(cloud, np.zeros(3), radius=0.01) == 1


def test_hand_inserts_table_top_took_the_points_in_the_old_box_and_not_in_its_own():
    small = dict(layouts=1, image_size=96, dense_points=1024, backend="raycast")
    old = measure_task("hand-insert", PointBudgetConfig(crop_box=OLD_BOX, **small))
    own = measure_task("hand-insert", PointBudgetConfig(**small))
    assert old["band_share"] > 0.6 and own["band_share"] < 0.2
    assert own["in_box"] < old["in_box"] / 3
    assert own["near_read"] > old["near_read"]
