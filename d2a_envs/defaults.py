"""Per-suite point-cloud defaults: cameras, image size, point budget and workspace box.

The boxes spend the point budget on the robot and the objects: Meta-World's box starts
5 mm above the table top (z = 0), so the flat table, the floor and the retaining walls at
y = 0.21 / 0.99 are dropped; Adroit's box keeps the hand and the objects above the
table. ``d2a viz pointcloud`` draws the box over the full cloud.

Cameras: Meta-World ``corner4`` has the pose of DP3's ``corner2`` view but sits closer, so
at 128 px the crop holds ~1200-3800 points (``corner2``: ~400-1200, often below N = 1024,
which would force repeated points). Adroit ``fixed`` gives ~1000-2500 points at 84 px
where ``vil_camera`` gives ~200-300 for Hammer and Pen (measured after reset, seed 0).
"""

from __future__ import annotations

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
