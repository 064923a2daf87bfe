"""Build D2A environments: the entry point behind every registered ``D2A-*`` id."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from importlib.metadata import entry_points
from typing import Any

import gymnasium as gym

from d2a_envs.defaults import default_config
from d2a_envs.read_steps import ReadSteps
from d2a_envs.sampling import CropBox
from d2a_envs.sensor import PointCloudConfig
from d2a_envs.suites.adroit import AdroitEnv
from d2a_envs.suites.base import SuiteEnv
from d2a_envs.suites.metaworld import MetaWorldEnv
from d2a_envs.wrappers import IMAGINED_KEY, ActionRepeat, CameraImageObservation, PointCloudObservation

_SUITE_ENVS: dict[str, type[SuiteEnv]] = {"metaworld": MetaWorldEnv, "adroit": AdroitEnv}
# Wrappers that packages above this one provide by name (``world_model``: the imagination
# wrapper of ``d2a_agents``), found through installed entry points: no import points upwards.
WRAPPER_ENTRY_POINTS = "d2a_envs.wrappers"


def plugin_wrapper(name: str) -> Callable[..., gym.Env]:
    """The wrapper an installed package registers as ``name`` in the ``d2a_envs.wrappers`` group."""
    found = [point for point in entry_points(group=WRAPPER_ENTRY_POINTS) if point.name == name]
    if not found:
        raise ImportError(f"no installed package provides the {name!r} wrapper (entry point group "
                          f"{WRAPPER_ENTRY_POINTS!r}); install d2a with its agents (pip install -e .)")
    return found[0].load()


def task_config(name: str) -> PointCloudConfig:
    """The point-cloud defaults of the task ``name`` (``hand-insert``, ``adroit-door``)."""
    from d2a_envs.tasks import get_task

    spec = get_task(name)
    return default_config(spec.suite, spec.task)


def env_crop_box(name: str, env_kwargs: Mapping[str, Any]) -> CropBox:
    """The box that task ``name``'s env made with ``env_kwargs`` crops to: theirs, or the task's default."""
    box = env_kwargs.get("crop_box")
    return CropBox.from_any(box) if box is not None else task_config(name).crop_box


def make_env(
    suite: str,
    task: str,
    *,
    cameras: str | Sequence[str] | None = None,
    image_size: int | tuple[int, int] | None = None,
    num_points: int | None = None,
    crop_box: CropBox | Sequence[Sequence[float]] | None = None,
    backend: str | None = None,
    with_rgb: bool | None = None,
    show_sites: bool | None = None,
    rgb_image_size: int | None = None,
    action_repeat: int = 1,
    state_obs: bool = True,
    physics_obs: bool = False,
    world_model: str | None = None,
    imagined_points: int | None = None,
    imagined_output: str | None = None,
    read_steps: Mapping[str, ReadSteps | Sequence[int]] | None = None,
) -> gym.Env:
    """A suite env with point-cloud observations; ``None`` arguments take the suite default.

    Prefer ``gym.make("D2A-MetaWorld-Hammer-v0", **kwargs)``, which adds the 200-step time
    limit; the keyword arguments are the same. ``world_model`` (a checkpoint of ``d2a train-wm``)
    adds ``imagined_point_cloud`` through the ``world_model`` wrapper plugin
    (:class:`~d2a_agents.world_model.observation.ImaginationWrapper`), of
    ``imagined_points`` points (default: ``num_points``; a policy that reads 64 points asks for 64,
    which spares a farthest-point pass over thousands of points at every step); ``imagined_output``
    ("future", the default, or "change") says what it holds.
    ``physics_obs`` (Adroit) adds the ``physics`` vector that the planning experts read.
    ``rgb_image_size`` adds ``image``, the first camera's colour view at that many pixels a side
    (:class:`~d2a_envs.wrappers.CameraImageObservation`, the input of ``--algo dp``).
    ``action_repeat`` holds each action for that many simulator steps
    (:class:`~d2a_envs.wrappers.ActionRepeat`; DP3's Adroit envs hold 2), observing once per action.
    """
    if suite not in _SUITE_ENVS:
        raise ValueError(f"unknown suite {suite!r}; choose one of {sorted(_SUITE_ENVS)}")
    config = default_config(suite, task).updated(
        cameras=cameras, image_size=image_size, num_points=num_points,
        crop_box=crop_box, backend=backend, with_rgb=with_rgb, show_sites=show_sites,
    )
    suite_kwargs = {"state_obs": state_obs}
    if physics_obs:  # the planning experts' input: Adroit only
        if suite != "adroit":
            raise ValueError(f"physics_obs is available for Adroit tasks, not {suite}")
        suite_kwargs["physics_obs"] = True
    cloud_steps, imagined_steps = observation_read_steps(read_steps)
    base = _SUITE_ENVS[suite](task, **suite_kwargs)
    env = PointCloudObservation(base if action_repeat == 1 else ActionRepeat(base, action_repeat), config, cloud_steps)
    if rgb_image_size is not None:
        env = CameraImageObservation(env, config.cameras[0], rgb_image_size, config.backend, config.show_sites)
    if (imagined_points is not None or imagined_output is not None) and world_model is None:
        raise ValueError("imagined_points and imagined_output need a world_model")
    if world_model is not None:
        from d2a_envs.tasks import TASKS

        name = next((spec.name for spec in TASKS if spec.suite == suite and spec.task == task), None)
        output = {} if imagined_output is None else {"output": imagined_output}
        if not cloud_steps.covers(imagined_steps):
            raise ValueError(f"the world model imagines from the present cloud: it cannot be read at fewer steps "
                             f"({cloud_steps}) than the imagined one ({imagined_steps})")
        env = plugin_wrapper("world_model")(env, world_model, task=name, num_points=imagined_points,
                                            read_steps=imagined_steps, **output)
    return env


def observation_read_steps(read_steps: Mapping[str, ReadSteps | Sequence[int]] | None) -> tuple[ReadSteps, ReadSteps]:
    """The steps at which ``point_cloud`` and ``imagined_point_cloud`` are read (every step
    unless given); a key other than these two is refused."""
    read_steps = dict(read_steps or {})
    unknown = set(read_steps) - {"point_cloud", IMAGINED_KEY}
    if unknown:
        raise ValueError(f"read_steps covers point_cloud and {IMAGINED_KEY} only, not {sorted(unknown)}")
    return ReadSteps.from_any(read_steps.get("point_cloud")), ReadSteps.from_any(read_steps.get(IMAGINED_KEY))
