"""Shared fixtures: importing d2a_envs first picks a headless GL platform for MuJoCo."""
# ruff: noqa: I001  (d2a_envs must be imported before mujoco: it sets MUJOCO_GL)

from __future__ import annotations

import os

import d2a_envs  # noqa: F401  (also registers the D2A ids)
import mujoco
import pytest

from d2a_envs.depth import RenderDepth

# A scene with known geometry: a sphere and a box, a spherical site (a marker, as Meta-World's
# goals are), seen by one camera, nothing else.
SPHERE_CENTRE, SPHERE_RADIUS = (0.0, 0.0, 0.5), 0.1
BOX_CENTRE, BOX_HALF = (0.35, 0.1, 0.35), 0.1
MARKER_CENTRE, MARKER_RADIUS = (-0.3, 0.0, 0.4), 0.05
KNOWN_SCENE_XML = f"""
<mujoco>
  <visual><global offwidth="256" offheight="256"/></visual>
  <worldbody>
    <light pos="0 -1 2" dir="0 0.5 -1"/>
    <geom name="ball" type="sphere" size="{SPHERE_RADIUS}" pos="{' '.join(map(str, SPHERE_CENTRE))}" rgba="1 0 0 1"/>
    <geom name="block" type="box" size="{BOX_HALF} {BOX_HALF} {BOX_HALF}" pos="{' '.join(map(str, BOX_CENTRE))}"
          rgba="0 1 0 1"/>
    <site name="marker" type="sphere" size="{MARKER_RADIUS}" pos="{' '.join(map(str, MARKER_CENTRE))}"
          rgba="0 0 1 1"/>
    <camera name="front" pos="0.1 -1.2 0.8" xyaxes="1 0 0 0 0.3 1" fovy="50"/>
  </worldbody>
</mujoco>
"""


@pytest.fixture
def known_scene() -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_string(KNOWN_SCENE_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


SMALL_ENV_KWARGS = {"image_size": 48, "num_points": 128}


@pytest.fixture(scope="session")
def reach_data(tmp_path_factory) -> str:
    """Two scripted Reach demonstrations at small settings, collected once per session.

    Shared and read-only: a test that changes a data set copies it first.
    """
    from collectors.collect import CollectConfig, collect

    out = tmp_path_factory.mktemp("data") / "reach"
    collect(CollectConfig(tasks=("reach",), out=str(out), episodes=2, env_kwargs=SMALL_ENV_KWARGS, progress=False))
    return str(out)


def _render_available() -> bool:
    try:
        model = mujoco.MjModel.from_xml_string(KNOWN_SCENE_XML)
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        backend = RenderDepth(8, 8)
        backend.capture(model, data, 0, with_rgb=False)
        backend.close()
        return True
    except RuntimeError:
        return False


RENDER_AVAILABLE = _render_available()
if os.environ.get("D2A_REQUIRE_RENDER") == "1" and not RENDER_AVAILABLE:
    raise RuntimeError("D2A_REQUIRE_RENDER=1 but the render backend cannot create a GL context here")
requires_render = pytest.mark.skipif(
    not RENDER_AVAILABLE, reason="no headless OpenGL (apt-get install libegl1 libgl1-mesa-dri libosmesa6)"
)
