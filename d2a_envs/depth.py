"""Depth (and colour) images of MuJoCo cameras from two interchangeable backends.

``raycast`` casts one ray per pixel centre with ``mujoco.mj_multiRay``: no OpenGL, cheap on
a CPU. ``render`` rasterises with MuJoCo's OpenGL renderer (EGL or OSMesa). Both see what
MuJoCo's renderer draws by default (geom and site groups 0-2): the sites include the goal
markers of Meta-World, which DP3 and MP1 clouds show too (without them Push's goal is
invisible). Both return the depth along the optical axis in metres, ``inf`` where the pixel
sees nothing.
"""

from __future__ import annotations

import atexit
import itertools
import os
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Protocol

import mujoco
import numpy as np

from d2a_envs.camera import camera_intrinsics, camera_pose
from d2a_envs.gl import bound_gl_platform, missing_gl_message
from d2a_envs.sampling import CropBox

DEPTH_BACKENDS = ("raycast", "render")


@dataclass
class CameraImage:
    """One camera's view: depth (H, W) in metres (``inf`` = nothing) and optional RGB in [0, 1]."""

    depth: np.ndarray
    rgb: np.ndarray | None = None


class DepthBackend(Protocol):
    """What the point-cloud sensor needs from a backend."""

    name: str

    def capture(
        self, model: mujoco.MjModel, data: mujoco.MjData, cam_id: int, with_rgb: bool,
        region: CropBox | None = None,
    ) -> CameraImage:
        """Depth (and RGB when asked) of camera ``cam_id`` in the current state.

        With ``region``, pixels whose ray cannot reach the box may be left at ``inf``: their
        points would be cropped anyway, and skipping them is the raycaster's main saving.
        """
        ...

    def colour(self, model: mujoco.MjModel, data: mujoco.MjData, cam_id: int) -> np.ndarray:
        """RGB (H, W, 3) in [0, 1] of camera ``cam_id``, without the depth image where the backend can skip it."""
        ...

    def close(self) -> None:
        """Release any resource (GL context) held by the backend."""
        ...


def visible_geom_groups() -> np.ndarray:
    """The geom groups MuJoCo draws by default (0, 1, 2): what a camera can see."""
    return np.asarray(mujoco.MjvOption().geomgroup, dtype=np.uint8)


def visible_sites(model: mujoco.MjModel) -> np.ndarray:
    """Ids of the sites MuJoCo draws by default: groups 0-2, not fully transparent."""
    groups = np.asarray(mujoco.MjvOption().sitegroup, dtype=bool)
    in_group = groups[np.clip(model.site_group, 0, len(groups) - 1)]
    return np.flatnonzero(in_group & (model.site_rgba[:, 3] > 0))


def cast_sites(
    model: mujoco.MjModel, data: mujoco.MjData, origin: np.ndarray, directions: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """(site id, ray parameter) of the nearest visible site on each ray; -1 / ``inf`` where none.

    ``mj_ray`` ignores sites, so each site is intersected on its own with ``mju_rayGeom``,
    only for the rays that pass within its bounding sphere (a goal marker covers a few pixels).
    """
    site_ids = np.full(len(directions), -1, dtype=np.int32)
    dist = np.full(len(directions), np.inf)
    norm2 = np.einsum("ij,ij->i", directions, directions)
    for site in visible_sites(model):
        centre = data.site_xpos[site] - origin
        along = directions @ centre
        miss2 = centre @ centre - along**2 / norm2
        bound = float(np.linalg.norm(model.site_size[site]))
        for ray in np.flatnonzero((miss2 <= bound**2) & (along > 0)):
            x = mujoco.mju_rayGeom(
                data.site_xpos[site], data.site_xmat[site], model.site_size[site], origin, directions[ray],
                int(model.site_type[site]),
            )
            if 0 <= x < dist[ray]:
                dist[ray], site_ids[ray] = x, site
    return site_ids, dist


def far_clip(model: mujoco.MjModel) -> float:
    """Far clipping distance of the model's renderer in metres."""
    return float(model.vis.map.zfar * model.stat.extent)


# mj_multiRay of MuJoCo < 3.5 (Meta-World pins 3.3.0) culls geoms with angular windows
# that break near the vertical: a top-down camera loses ~9 % of its pixels (walls, table
# edges), while oblique cameras lose < 0.2 %. Cameras with a ray steeper than this are cast
# one ray at a time with mj_ray, which has no such culling (about 4 us per ray).
MULTIRAY_MAX_ELEVATION_DEG = 60.0
MULTIRAY_IS_EXACT = tuple(int(x) for x in mujoco.__version__.split(".")[:2]) >= (3, 5)


def default_ray_threads() -> int:
    """Threads for ray casting: MuJoCo releases the GIL, so casting scales with cores."""
    return max(1, min(4, len(os.sched_getaffinity(0))))


class RaycastDepth:
    """Depth by ray casting from the camera through every pixel centre (no GL needed).

    Rays are cast in ``threads`` chunks in parallel; each ray is independent, so the image
    does not depend on the number of threads.
    """

    name = "raycast"

    def __init__(self, width: int, height: int, threads: int | None = None, show_sites: bool = True) -> None:
        self.width, self.height = width, height
        self.threads = threads or default_ray_threads()
        self.show_sites = show_sites
        self._geom_groups = visible_geom_groups()
        self._pool: ThreadPoolExecutor | None = None
        self._pool_pid: int | None = None

    def _executor(self) -> ThreadPoolExecutor:
        # Threads do not survive fork: a forked copy makes its own pool.
        if self._pool is None or self._pool_pid != os.getpid():
            self._pool, self._pool_pid = ThreadPoolExecutor(self.threads), os.getpid()
        return self._pool

    def _cast(self, model: mujoco.MjModel, data: mujoco.MjData, origin: np.ndarray, vec: np.ndarray):
        """(geom id, distance) of every ray; id -1 where nothing is hit."""
        geom_ids = np.full(len(vec), -1, dtype=np.int32)
        dist = np.empty(len(vec), dtype=np.float64)
        if len(vec) == 0:
            return geom_ids, dist
        exact_multiray = MULTIRAY_IS_EXACT or not _has_steep_ray(vec)

        def cast_chunk(chunk: slice) -> None:
            ids, lengths, rays = geom_ids[chunk], dist[chunk], np.ascontiguousarray(vec[chunk])
            if exact_multiray:
                mujoco.mj_multiRay(
                    model, data, origin, rays.reshape(-1), self._geom_groups, 1, -1, ids, lengths, len(rays),
                    far_clip(model),
                )
                return
            hit_id = np.empty(1, dtype=np.int32)
            for i, ray in enumerate(rays):
                lengths[i] = mujoco.mj_ray(model, data, origin, ray, self._geom_groups, 1, -1, hit_id)
                ids[i] = hit_id[0]

        bounds = np.linspace(0, len(vec), self.threads + 1).astype(int)
        chunks = [slice(a, b) for a, b in itertools.pairwise(bounds) if b > a]
        if len(chunks) <= 1:
            for chunk in chunks:
                cast_chunk(chunk)
        else:
            list(self._executor().map(cast_chunk, chunks))
        return geom_ids, dist

    def capture(
        self, model: mujoco.MjModel, data: mujoco.MjData, cam_id: int, with_rgb: bool,
        region: CropBox | None = None,
    ) -> CameraImage:
        pose = camera_pose(data, cam_id)
        # Directions keep z = -1 in the camera frame, so the ray parameter is the depth.
        all_vec = camera_intrinsics(model, cam_id, self.width, self.height).ray_directions() @ pose.rotation.T
        cast = np.ones(len(all_vec), dtype=bool) if region is None else rays_meet_box(pose.position, all_vec, region)
        vec = all_vec[cast]
        geom_ids, dist = self._cast(model, data, pose.position, vec)
        dist[geom_ids < 0] = np.inf
        colours = np.zeros((len(vec), 3))
        if with_rgb:
            colours[geom_ids >= 0] = geom_colours(model)[geom_ids[geom_ids >= 0]]
        if self.show_sites:
            site_ids, site_dist = cast_sites(model, data, pose.position, vec)
            nearer = site_dist < dist
            dist[nearer] = site_dist[nearer]
            colours[nearer] = model.site_rgba[site_ids[nearer], :3]
        depth = np.full(len(all_vec), np.inf)
        depth[cast] = dist
        rgb = None
        if with_rgb:
            rgb = np.zeros((len(all_vec), 3))
            rgb[cast] = colours
            rgb = rgb.reshape(self.height, self.width, 3)
        return CameraImage(depth=depth.reshape(self.height, self.width), rgb=rgb)

    def colour(self, model: mujoco.MjModel, data: mujoco.MjData, cam_id: int) -> np.ndarray:
        return self.capture(model, data, cam_id, with_rgb=True).rgb  # the colours come from the cast depth

    def close(self) -> None:
        if self._pool is not None and self._pool_pid == os.getpid():
            self._pool.shutdown()
        self._pool = None

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_pool"], state["_pool_pid"] = None, None
        return state


def rays_meet_box(origin: np.ndarray, directions: np.ndarray, box: CropBox) -> np.ndarray:
    """Which rays ``origin + t * direction`` (t >= 0) pass through the box (slab test)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t_low = (np.asarray(box.low) - origin) / directions
        t_high = (np.asarray(box.high) - origin) / directions
    t_near = np.nan_to_num(np.minimum(t_low, t_high), nan=-np.inf).max(axis=1)
    t_far = np.nan_to_num(np.maximum(t_low, t_high), nan=np.inf).min(axis=1)
    return t_far >= np.maximum(t_near, 0.0)


def _has_steep_ray(directions: np.ndarray) -> bool:
    """Whether any ray points within ``90 - MULTIRAY_MAX_ELEVATION_DEG`` degrees of vertical."""
    sin_elevation = np.abs(directions[:, 2]) / np.linalg.norm(directions, axis=1)
    return bool(sin_elevation.max() > np.sin(np.radians(MULTIRAY_MAX_ELEVATION_DEG)))


def geom_colours(model: mujoco.MjModel) -> np.ndarray:
    """Flat RGB of every geom (its material's colour where it has one), shape (ngeom, 3)."""
    colours = model.geom_rgba[:, :3].copy()
    has_material = model.geom_matid >= 0
    colours[has_material] = model.mat_rgba[model.geom_matid[has_material], :3]
    return colours


# Process that created the first GL context. A GL driver's threads and locks do not survive
# fork: a forked child that renders after its parent did can hang (seen with Mesa's EGL).
_gl_owner_pid: int | None = None


def _claim_gl_for_this_process() -> None:
    global _gl_owner_pid
    if _gl_owner_pid is not None and _gl_owner_pid != os.getpid():
        raise RuntimeError(
            "the 'render' backend cannot create a GL context in a process forked after its parent "
            f"(pid {_gl_owner_pid}) already rendered: start workers with the 'spawn' method, e.g. "
            "gymnasium.vector.AsyncVectorEnv(env_fns, context='spawn'), or use backend='raycast'"
        )
    _gl_owner_pid = os.getpid()


# Open renderers, closed at exit before the GL display goes: MuJoCo's EGL context registers
# eglTerminate with atexit when it is first made, and a renderer collected after that raises
# EGLError during interpreter shutdown. atexit runs last-registered first, so a hook registered
# after the first context closes the renderers while the display is still there.
_open_renderers: weakref.WeakSet[RenderDepth] = weakref.WeakSet()
_exit_hook_registered = False


def _track_for_exit(backend: RenderDepth) -> None:
    global _exit_hook_registered
    _open_renderers.add(backend)
    if not _exit_hook_registered:
        atexit.register(_close_open_renderers)
        _exit_hook_registered = True


def _close_open_renderers() -> None:
    for backend in list(_open_renderers):
        backend.close()


# Scene effects the ``render`` backend leaves out of its colour images (see RenderDepth).
PLAIN_RENDER_OFF = (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION, mujoco.mjtRndFlag.mjRND_SKYBOX)


class RenderDepth:
    """Depth from MuJoCo's OpenGL renderer, created lazily so forked workers stay safe.

    Its colour images are lit and textured but drawn without shadows, reflections or the
    skybox: with them a software renderer (OSMesa, EGL on llvmpipe) takes about 8x longer per
    image (200 against 26 ms at 84 pixels, one core) for what a policy does not need.
    """

    name = "render"

    def __init__(self, width: int, height: int, show_sites: bool = True) -> None:
        platform = bound_gl_platform()
        if platform is None or (platform in ("glfw", "glx") and not os.environ.get("DISPLAY")):
            raise RuntimeError(missing_gl_message(platform))
        self.width, self.height = width, height
        self._renderer: mujoco.Renderer | None = None
        self._model: mujoco.MjModel | None = None
        self._option = mujoco.MjvOption()
        if not show_sites:
            self._option.sitegroup[:] = 0

    def _get_renderer(self, model: mujoco.MjModel) -> mujoco.Renderer:
        if self._renderer is None or self._model is not model:
            self.close()
            global_vis = model.vis.global_
            global_vis.offwidth = max(global_vis.offwidth, self.width)
            global_vis.offheight = max(global_vis.offheight, self.height)
            _claim_gl_for_this_process()
            try:
                self._renderer = mujoco.Renderer(model, height=self.height, width=self.width)
            except Exception as error:  # GL context creation fails in many library-specific ways
                raise RuntimeError(f"{missing_gl_message(bound_gl_platform())} (cause: {error})") from error
            for effect in PLAIN_RENDER_OFF:
                self._renderer.scene.flags[effect] = False
            self._model = model
            _track_for_exit(self)
        return self._renderer

    def capture(
        self, model: mujoco.MjModel, data: mujoco.MjData, cam_id: int, with_rgb: bool,
        region: CropBox | None = None,
    ) -> CameraImage:
        renderer = self._get_renderer(model)
        renderer.update_scene(data, camera=cam_id, scene_option=self._option)
        renderer.enable_depth_rendering()
        depth = renderer.render().astype(np.float64)
        depth[depth >= 0.999 * far_clip(model)] = np.inf
        return CameraImage(depth=depth, rgb=self._render_colour(renderer) if with_rgb else None)

    def colour(self, model: mujoco.MjModel, data: mujoco.MjData, cam_id: int) -> np.ndarray:
        renderer = self._get_renderer(model)
        renderer.update_scene(data, camera=cam_id, scene_option=self._option)
        return self._render_colour(renderer)

    @staticmethod
    def _render_colour(renderer: mujoco.Renderer) -> np.ndarray:
        renderer.disable_depth_rendering()
        return renderer.render().astype(np.float32) / 255.0

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
        self._renderer, self._model = None, None

    def __getstate__(self) -> dict:
        # A GL context cannot cross a process boundary; the copy creates its own lazily.
        state = self.__dict__.copy()
        state["_renderer"], state["_model"] = None, None
        return state


def make_depth_backend(name: str, width: int, height: int, show_sites: bool = True) -> DepthBackend:
    """Backend by name: ``raycast`` or ``render``."""
    if name == "raycast":
        return RaycastDepth(width, height, show_sites=show_sites)
    if name == "render":
        return RenderDepth(width, height, show_sites=show_sites)
    raise ValueError(f"unknown depth backend {name!r}; choose one of {DEPTH_BACKENDS}")
