"""Camera maths and depth backends against independent geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from d2a_envs.camera import CameraPose, PinholeIntrinsics, backproject, camera_id, camera_intrinsics, camera_pose
from d2a_envs.depth import RaycastDepth, RenderDepth, rays_meet_box
from d2a_envs.sampling import CropBox
from tests.conftest import (
    BOX_CENTRE,
    BOX_HALF,
    MARKER_CENTRE,
    MARKER_RADIUS,
    SPHERE_CENTRE,
    SPHERE_RADIUS,
    requires_render,
)


def test_intrinsics_by_hand():
    # fovy = 90 deg and H = 4: f = 4 / (2 tan 45) = 2; pixel (row 0, col 0) centre is (0.5, 0.5).
    intrinsics = PinholeIntrinsics.from_fovy(90.0, width=6, height=4)
    assert intrinsics.focal == pytest.approx(2.0)
    rays = intrinsics.ray_directions().reshape(4, 6, 3)
    np.testing.assert_allclose(rays[0, 0], [(0.5 - 3) / 2, -(0.5 - 2) / 2, -1.0])
    np.testing.assert_allclose(rays[3, 5], [(5.5 - 3) / 2, -(3.5 - 2) / 2, -1.0])


def test_backproject_by_hand():
    # Camera at (1, 2, 3) looking along world +y: camera x = world x, camera y = world z,
    # camera z (backwards, opposite the view) = world -y. Columns are the camera axes.
    rotation = np.column_stack([[1, 0, 0], [0, 0, 1], [0, -1, 0]]).astype(float)
    pose = CameraPose(position=np.array([1.0, 2.0, 3.0]), rotation=rotation)
    intrinsics = PinholeIntrinsics.from_fovy(90.0, width=2, height=2)  # f = 1
    depth = np.array([[2.0, np.inf], [np.inf, np.inf]])
    points = backproject(depth, intrinsics, pose)
    # Pixel (0, 0): camera-frame direction (-0.5, 0.5, -1) * 2 = (-1, 1, -2).
    # 2 m along +y, 1 m left, 1 m up:
    np.testing.assert_allclose(points, [[1.0 - 1.0, 2.0 + 2.0, 3.0 + 1.0]], atol=1e-12)


def _to_marker(points: np.ndarray) -> np.ndarray:
    return np.abs(np.linalg.norm(points - MARKER_CENTRE, axis=1) - MARKER_RADIUS)


def _surface_error(points: np.ndarray) -> np.ndarray:
    """Distance of each point to the nearest of the three known surfaces."""
    to_sphere = np.abs(np.linalg.norm(points - SPHERE_CENTRE, axis=1) - SPHERE_RADIUS)
    offset = np.abs(points - BOX_CENTRE) - BOX_HALF
    outside = np.linalg.norm(np.maximum(offset, 0.0), axis=1)
    to_box = np.where(outside > 0, outside, np.abs(offset.max(axis=1)))
    return np.minimum(np.minimum(to_sphere, to_box), _to_marker(points))


def _scene_points(backend, model, data) -> np.ndarray:
    cam = camera_id(model, "front")
    image = backend.capture(model, data, cam, with_rgb=False)
    intrinsics = camera_intrinsics(model, cam, backend.width, backend.height)
    return backproject(image.depth, intrinsics, camera_pose(data, cam))


def test_raycast_points_lie_on_known_surfaces(known_scene):
    model, data = known_scene
    points = _scene_points(RaycastDepth(96, 64), model, data)
    assert len(points) > 200
    assert _surface_error(points).max() < 1e-6
    on_sphere = np.abs(np.linalg.norm(points - SPHERE_CENTRE, axis=1) - SPHERE_RADIUS) < 1e-6
    assert 50 < on_sphere.sum() < len(points)  # both objects are seen
    assert (_to_marker(points) < 1e-6).sum() > 20  # and the site, which mj_ray alone cannot hit


@pytest.mark.parametrize("backend", ["raycast", pytest.param("render", marks=requires_render)])
def test_hidden_sites_leave_the_marker_out(known_scene, backend):
    model, data = known_scene
    make = RaycastDepth if backend == "raycast" else RenderDepth
    shown = _scene_points(make(96, 64), model, data)
    hidden = _scene_points(make(96, 64, show_sites=False), model, data)
    assert (_to_marker(shown) < 0.002).sum() > 20
    assert (_to_marker(hidden) < 0.002).sum() == 0


@requires_render
def test_render_points_lie_on_known_surfaces(known_scene):
    model, data = known_scene
    points = _scene_points(RenderDepth(96, 64), model, data)
    errors = _surface_error(points)
    # The renderer tessellates the sphere and quantises depth: millimetres, not micrometres.
    assert np.quantile(errors, 0.99) < 0.002


def test_raycast_colours_come_from_the_hit_geom(known_scene):
    model, data = known_scene
    image = RaycastDepth(48, 32).capture(model, data, camera_id(model, "front"), with_rgb=True)
    seen = np.isfinite(image.depth)
    colours = {tuple(c) for c in image.rgb[seen].round(3)}
    assert colours == {(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)}
    assert np.all(image.rgb[~seen] == 0.0)


def test_slab_test_by_hand():
    box = CropBox(low=(-1, -1, -1), high=(1, 1, 1))
    origin = np.array([0.0, -5.0, 0.0])
    directions = np.array([[0, 1, 0], [0, -1, 0], [1, 1, 0], [0.1, 1, 0], [1, 0, 0]], dtype=float)
    # Straight at the box, away from it, diagonal passing by (x = 5 at y = 0), slightly tilted, parallel outside.
    np.testing.assert_array_equal(rays_meet_box(origin, directions, box), [True, False, False, True, False])
    inside = rays_meet_box(np.zeros(3), directions, box)
    assert inside.all()  # every ray from inside the box meets it


def test_culled_raycast_keeps_every_point_in_the_box(known_scene):
    model, data = known_scene
    box = CropBox(low=(-0.2, -0.2, 0.3), high=(0.2, 0.2, 0.7))  # around the sphere only
    backend = RaycastDepth(96, 64)
    cam = camera_id(model, "front")
    full = backend.capture(model, data, cam, with_rgb=False).depth
    culled = backend.capture(model, data, cam, with_rgb=False, region=box).depth
    intrinsics, pose = camera_intrinsics(model, cam, 96, 64), camera_pose(data, cam)
    full_points = backproject(full, intrinsics, pose)
    culled_points = backproject(culled, intrinsics, pose)
    np.testing.assert_array_equal(full_points[box.contains(full_points)], culled_points[box.contains(culled_points)])
    assert np.isfinite(culled).sum() < np.isfinite(full).sum()  # the box really culled rays


def test_focal_length_matches_fovy_convention(known_scene):
    model, _ = known_scene
    intrinsics = camera_intrinsics(model, camera_id(model, "front"), 100, 80)
    assert intrinsics.focal == pytest.approx(80 / (2 * math.tan(math.radians(50) / 2)))


@pytest.mark.parametrize("camera", ["corner4", "topview"])
def test_raycast_image_does_not_depend_on_thread_count(camera):
    import gymnasium as gym

    env = gym.make("D2A-MetaWorld-Assembly-v0", image_size=16, num_points=8)
    env.reset(seed=0)
    model, data = env.unwrapped.model, env.unwrapped.data
    cam = camera_id(model, camera)
    images = [RaycastDepth(64, 48, threads=n).capture(model, data, cam, with_rgb=True) for n in (1, 3)]
    np.testing.assert_array_equal(images[0].depth, images[1].depth)
    np.testing.assert_array_equal(images[0].rgb, images[1].rgb)
