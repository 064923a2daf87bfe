"""Where a task's point budget goes: its object's share, and any flat surface that takes the rest.

A policy reads N points farthest-point sampled from a dense cloud. When a flat surface inside
the crop box holds most of the dense cloud (Hand-Insert's table top at z = 5 cm, before its box
was raised above it), sampling spreads the N points over that surface and the object gets none.
This bench prints, per task at reset over a few new layouts: the points in the box, the share
of the dense cloud in its densest 5 mm band of height, and the points within 4 cm of the object
in the dense cloud and among the N the policy reads.

The object's position is the first one of Meta-World's state (``state[4:7]``): a body's origin,
which for a few tasks lies off the visible part (Dial-Turn's lies beside the dial), so a count
of 0 there is read with the picture (``d2a viz pointcloud --task T --num-points N``).
"""

from __future__ import annotations

import statistics
from dataclasses import dataclass

import numpy as np

import d2a_envs
from d2a_envs.sampling import farthest_point_indices

BAND = 0.005  # height band, metres
NEAR_OBJECT = 0.04  # radius around the object's position, metres


@dataclass(frozen=True)
class PointBudgetConfig:
    """What ``d2a bench points`` measures (the grids' dense clouds by default)."""

    tasks: tuple[str, ...] | None = None  # default: the Meta-World tasks of Table I
    points: int = 128  # what the policy reads
    layouts: int = 5
    first_seed: int = 100000  # the grids' evaluation layouts
    image_size: int = 256
    dense_points: int = 4096
    backend: str = "render"
    crop_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None  # default: each task's own


def densest_band_share(points: np.ndarray, band: float = BAND) -> float:
    """The largest share of the points whose heights fall in one ``band``-high slice (bins from the lowest)."""
    heights = points[:, 2] - points[:, 2].min()
    counts = np.bincount(np.floor(heights / band).astype(int))
    return float(counts.max() / len(points))


def points_near(points: np.ndarray, centre: np.ndarray, radius: float = NEAR_OBJECT) -> int:
    """How many points lie within ``radius`` of ``centre``."""
    return int(np.sum(np.linalg.norm(points[:, :3] - centre, axis=1) < radius))


def measure_task(name: str, config: PointBudgetConfig) -> dict[str, float | str]:
    """Medians over the layouts of one task's figures (see the module docstring)."""
    spec = d2a_envs.get_task(name)
    if spec.suite != "metaworld":
        raise ValueError(f"{name}: the point-budget bench reads Meta-World's object position; {spec.suite} has none")
    env = d2a_envs.make_env(spec.suite, spec.task, image_size=config.image_size, num_points=config.dense_points,
                            backend=config.backend, crop_box=config.crop_box)
    in_box, band_share, near_dense, near_read = [], [], [], []
    for seed in range(config.first_seed, config.first_seed + config.layouts):
        observation, info = env.reset(seed=seed)
        cloud, target = observation["point_cloud"][:, :3], observation["state"][4:7]
        read = cloud[farthest_point_indices(cloud, config.points)]
        in_box.append(info["num_points_in_crop"])
        band_share.append(densest_band_share(cloud))
        near_dense.append(points_near(cloud, target))
        near_read.append(points_near(read, target))
    env.close()
    return dict(task=name, difficulty=spec.difficulty or "-", in_box=statistics.median(in_box),
                band_share=statistics.median(band_share), near_dense=statistics.median(near_dense),
                near_read=statistics.median(near_read))


def run(config: PointBudgetConfig = PointBudgetConfig()) -> list[dict[str, float | str]]:
    """Measure every task; prints a markdown table and returns its rows."""
    names = config.tasks or tuple(spec.name for spec in d2a_envs.list_tasks(suite="metaworld", table1=True))
    rows = [measure_task(name, config) for name in names]
    print(f"\nAt reset, medians over {config.layouts} layouts from seed {config.first_seed}: {config.image_size}-px "
          f"{config.backend} depth, {config.dense_points}-point clouds, {config.points} read by farthest-point "
          "sampling" + (f", crop box {config.crop_box}" if config.crop_box else ", each task's own crop box") + "\n")
    print(f"| task | group | points in the box | densest {BAND * 1000:g} mm band | near the object "
          f"(of {config.dense_points}) | near the object (of {config.points}) |")
    print("| --- | --- | --- | --- | --- | --- |")
    for row in rows:
        print(f"| {row['task']} | {row['difficulty']} | {row['in_box']:.0f} | {100 * row['band_share']:.0f} % | "
              f"{row['near_dense']:g} | {row['near_read']:g} |")
    return rows
