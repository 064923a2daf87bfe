"""Choose MuJoCo's OpenGL platform before MuJoCo is imported.

MuJoCo binds its GL platform (``MUJOCO_GL``) once, at import time. On a headless machine
the default (GLFW) cannot open a context, and asking for EGL where ``libEGL`` is missing
makes ``import mujoco`` itself fail. This module picks a platform that can load, so that
importing :mod:`d2a_envs` never breaks and the ``render`` backend can explain what to
install when no GL library is present. It also sets how many threads a software renderer
draws with (:func:`software_render_threads`).
"""

from __future__ import annotations

import ctypes.util
import os

# Debian packages that provide each platform's library.
GL_PACKAGES = {"egl": "libegl1 libgl1-mesa-dri", "osmesa": "libosmesa6"}
_LIBRARIES = {"egl": "EGL", "osmesa": "OSMesa"}


def available_gl_platforms() -> list[str]:
    """Headless GL platforms whose shared library can be found on this machine."""
    return [name for name, lib in _LIBRARIES.items() if ctypes.util.find_library(lib)]


def configure_mujoco_gl() -> str:
    """Set ``MUJOCO_GL`` to a loadable headless platform unless the user already chose one.

    Returns the value in force. With no GL library at all, GL is disabled so that
    ``import mujoco`` still works; the raycast depth backend needs no GL.
    """
    if "MUJOCO_GL" not in os.environ:
        platforms = available_gl_platforms()
        os.environ["MUJOCO_GL"] = platforms[0] if platforms else "disable"
    return os.environ["MUJOCO_GL"]


def bound_gl_platform() -> str | None:
    """The GL platform MuJoCo actually bound at import (``egl``, ``osmesa``, ``glfw``...),
    or ``None`` when GL is disabled. It can differ from ``MUJOCO_GL`` if MuJoCo was imported
    before this package set it."""
    import mujoco

    context = getattr(mujoco, "GLContext", None)
    return None if context is None else context.__module__.rsplit(".", 1)[-1]


def missing_gl_message(platform: str | None) -> str:
    """Explain how to make the render backend available on Debian/Ubuntu."""
    packages = " ".join(GL_PACKAGES.values())
    return (
        f"the 'render' depth backend needs a headless OpenGL platform, but MuJoCo bound "
        f"{platform or 'no GL'!r}; install one with `apt-get install {packages}` and set "
        f"MUJOCO_GL=egl (or osmesa) before mujoco is first imported (importing d2a_envs first "
        f"does it), or use backend='raycast', which needs no GL"
    )


def software_render_threads(threads: int) -> str:
    """Tell Mesa's software rasteriser (llvmpipe: what EGL and OSMesa draw with on a machine
    without a GPU) how many threads to draw with, unless ``LP_NUM_THREADS`` is already set.

    A one-thread run draws in its calling thread (``0``) rather than with llvmpipe's default pool
    of one thread per core, whose threads beside other busy runs mostly wait on each other: the
    clouds are the same to the bit and a step took 0.82-0.99x the time in three comparisons
    (``d2a bench envs --render-threads``; docs/results.md). Mesa reads the variable when the process's first GL
    context is made, so call this before anything renders. Returns the value in force.
    """
    if threads < 1:
        raise ValueError(f"threads must be at least 1, got {threads}")
    os.environ.setdefault("LP_NUM_THREADS", "0" if threads == 1 else str(threads))
    return os.environ["LP_NUM_THREADS"]
