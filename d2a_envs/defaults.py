"""Per-suite point-cloud defaults: cameras, image size, point budget and workspace box.

The boxes spend the point budget on the robot and the objects: Meta-World's box starts
5 mm above the table top (z = 0), so the flat table, the floor and the retaining walls at
y = 0.21 / 0.99 are dropped; Adroit's box keeps the hand and the objects above the
table. Hand-Insert and Sweep-Into stand on a table with a hole whose top is at z = 5 cm; their
box starts 5 mm above it (:func:`default_config`), or that flat top would take about 80 % of
the points and leave the block none of 128. Pick-Out-Of-Hole's top is raised too, but its
object starts in the hole below it, so it keeps the suite's box.
``d2a viz pointcloud`` draws the box over the full cloud.

Cameras: Meta-World ``corner4`` has the pose of DP3's ``corner2`` view but sits closer, so
at 128 px the crop holds ~1200-3800 points (``corner2``: ~400-1200, often below N = 1024,
which would force repeated points). Adroit ``fixed`` gives ~1000-2500 points at 84 px
where ``vil_camera`` gives ~200-300 for Hammer and Pen (measured after reset, seed 0).
"""

from __future__ import annotations

from dataclasses import replace

from d2a_envs.sampling import CropBox
from d2a_envs.sensor import PointCloudConfig

SUITE_DEFAULTS: dict[str, PointCloudConfig] = {
    "metaworld": PointCloudConfig(
        cameras=("corner4",),
        image_size=(128, 128),
        num_points=1024,
        crop_box=CropBox(low=(-0.6, 0.25, 0.005), high=(0.6, 0.97, 0.7)),
    ),
    "adroit": PointCloudConfig(
        cameras=("fixed",),
        image_size=(84, 84),
        num_points=512,
        crop_box=CropBox(low=(-0.6, -0.6, 0.005), high=(0.6, 0.6, 0.9)),
    ),
}

# DP3/MP1 protocol: 200 control steps per episode in both suites.
DEFAULT_MAX_EPISODE_STEPS = 200

# Meta-World tasks whose table top is at z = 5 cm instead of 0 and whose objects stand on it.
RAISED_TABLE_TASKS = frozenset({"hand-insert-v3", "sweep-into-v3"})
_RAISED_TABLE_TOP = 0.05
_FLOOR_ABOVE_TABLE = 0.005


def default_config(suite: str, task: str) -> PointCloudConfig:
    """The point-cloud defaults of one task (``suite``, simulator ``task`` name, e.g. ``hand-insert-v3``).

    Its suite's defaults, with the crop box's floor 5 mm above the table top where the task
    raises it, so the points go to the robot and the objects in every task.
    """
    if suite not in SUITE_DEFAULTS:
        raise ValueError(f"unknown suite {suite!r}; choose one of {sorted(SUITE_DEFAULTS)}")
    config = SUITE_DEFAULTS[suite]
    if suite != "metaworld" or task not in RAISED_TABLE_TASKS:
        return config
    low = config.crop_box.low
    floor = _RAISED_TABLE_TOP + _FLOOR_ABOVE_TABLE
    return replace(config, crop_box=CropBox(low=(low[0], low[1], floor), high=config.crop_box.high))
