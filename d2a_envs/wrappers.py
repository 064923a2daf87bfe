"""Gymnasium wrappers: the point-cloud observation, a camera's colour image, per-episode seeds,
episodes that end at success."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from d2a_envs.camera import camera_id
from d2a_envs.depth import make_depth_backend
from d2a_envs.read_steps import ReadSteps, unread_observation
from d2a_envs.sensor import PointCloudConfig, PointCloudSensor

# The colour image observation of 2D image policies (``--algo dp``).
IMAGE_KEY = "image"
# The second cloud of the imagining policies: a world model's imagined future
# (``d2a_agents.world_model.observation``) or the simulator's true one (``collectors.expert_future``).
IMAGINED_KEY = "imagined_point_cloud"


def point_cloud_space(config: PointCloudConfig) -> spaces.Box:
    """Box space of a (num_points, 3 or 6) cloud: xyz inside the crop box, rgb in [0, 1]."""
    low = np.array(config.crop_box.low + (0.0, 0.0, 0.0)[: config.point_dim - 3], dtype=np.float32)
    high = np.array(config.crop_box.high + (1.0, 1.0, 1.0)[: config.point_dim - 3], dtype=np.float32)
    shape = (config.num_points, config.point_dim)
    return spaces.Box(np.broadcast_to(low, shape), np.broadcast_to(high, shape), shape, np.float32)


class PointCloudObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Add ``point_cloud`` (N x 3, or N x 6 with RGB) to a suite env's ``Dict`` observation.

    The wrapped env must expose MuJoCo ``model`` and ``data`` on ``env.unwrapped``. Filling
    (when the crop holds fewer than N points) draws from the base env's seeded generator,
    so ``reset(seed=s)`` reproduces the cloud; ``info["num_points_in_crop"]`` reports how
    many distinct points the crop held. With ``read_steps``
    (:class:`~d2a_envs.read_steps.ReadSteps`), the steps it skips are not rendered: their cloud
    is NaN and their ``num_points_in_crop`` -1 (the other steps' clouds are the same).

    Example:
        >>> env = PointCloudObservation(MetaWorldEnv("hammer-v3"), SUITE_DEFAULTS["metaworld"])
        >>> obs, info = env.reset(seed=0)
        >>> obs["point_cloud"].shape
        (1024, 3)
    """

    def __init__(self, env: gym.Env, config: PointCloudConfig, read_steps: ReadSteps | None = None) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, config=config, read_steps=read_steps)
        gym.Wrapper.__init__(self, env)
        if not isinstance(env.observation_space, spaces.Dict):
            raise TypeError(f"PointCloudObservation needs a Dict observation space, got {env.observation_space}")
        self.config = config
        self.read_steps = ReadSteps.from_any(read_steps)
        self._step = 0
        self.sensor = PointCloudSensor(config)
        self.sensor.validate(env.unwrapped.model)
        self.observation_space = spaces.Dict({**env.observation_space.spaces, "point_cloud": point_cloud_space(config)})

    def _add_cloud(self, observation: dict[str, np.ndarray], info: dict[str, Any]) -> dict[str, np.ndarray]:
        if not self.read_steps(self._step):
            info["num_points_in_crop"] = -1
            return {**observation, "point_cloud": unread_observation(self.observation_space["point_cloud"])}
        base = self.env.unwrapped
        reading = self.sensor.read(base.model, base.data, base.np_random)
        info["num_points_in_crop"] = reading.num_in_crop
        return {**observation, "point_cloud": reading.points}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        observation, info = self.env.reset(seed=seed, options=options)
        self._step = 0
        return self._add_cloud(observation, info), info

    def step(self, action: np.ndarray):
        observation, reward, terminated, truncated, info = self.env.step(action)
        self._step += 1
        return self._add_cloud(observation, info), reward, terminated, truncated, info

    def close(self) -> None:
        self.sensor.close()
        super().close()


class CameraImageObservation(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Add ``image``: one camera's colour view, (size, size, 3) uint8, the input of 2D policies.

    The same depth backends draw it: ``render`` gives MuJoCo's lit image, ``raycast`` the flat
    colour of the geom (or visible site) each pixel sees, black where it sees nothing (no
    lighting, no OpenGL).

    Example:
        >>> env = CameraImageObservation(MetaWorldEnv("hammer-v3"), camera="corner4", size=84)
        >>> env.reset(seed=0)[0]["image"].shape
        (84, 84, 3)
    """

    def __init__(self, env: gym.Env, camera: str, size: int, backend: str = "raycast", show_sites: bool = True) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, camera=camera, size=size, backend=backend, show_sites=show_sites)
        gym.Wrapper.__init__(self, env)
        if not isinstance(env.observation_space, spaces.Dict):
            raise TypeError(f"CameraImageObservation needs a Dict observation space, got {env.observation_space}")
        if isinstance(size, bool) or int(size) != size or size < 8:
            raise ValueError(f"the image size must be an integer of at least 8 pixels, got {size!r}")
        self._camera = camera_id(env.unwrapped.model, camera)
        self._backend = make_depth_backend(backend, int(size), int(size), show_sites)
        image_space = spaces.Box(0, 255, (int(size), int(size), 3), np.uint8)
        self.observation_space = spaces.Dict({**env.observation_space.spaces, IMAGE_KEY: image_space})

    def _add_image(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        base = self.env.unwrapped
        rgb = self._backend.colour(base.model, base.data, self._camera)
        return {**observation, IMAGE_KEY: np.round(np.clip(rgb, 0.0, 1.0) * 255).astype(np.uint8)}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        observation, info = self.env.reset(seed=seed, options=options)
        return self._add_image(observation), info

    def step(self, action: np.ndarray):
        observation, reward, terminated, truncated, info = self.env.step(action)
        return self._add_image(observation), reward, terminated, truncated, info

    def close(self) -> None:
        self._backend.close()
        super().close()


class ActionRepeat(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Hold each action for ``repeats`` simulator steps, as DP3's Adroit envs hold 2.

    A step returns the last observation, the rewards summed, and ``success`` true when any of
    the held steps succeeded; it stops early at termination or truncation. A time limit
    outside this wrapper counts the held steps as one.
    """

    def __init__(self, env: gym.Env, repeats: int) -> None:
        if isinstance(repeats, bool) or int(repeats) != repeats or repeats < 1:
            raise ValueError(f"an action is held for a positive whole number of steps, not {repeats!r}")
        gym.utils.RecordConstructorArgs.__init__(self, repeats=repeats)
        gym.Wrapper.__init__(self, env)
        self.repeats = int(repeats)

    def step(self, action: np.ndarray):
        total, success = 0.0, False
        for _ in range(self.repeats):
            observation, reward, terminated, truncated, info = self.env.step(action)
            total += float(reward)
            success = success or bool(info.get("success", False))
            if terminated or truncated:
                break
        return observation, total, terminated, truncated, {**info, "success": success}


class SeedEachReset(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Give every episode its own seed: after ``reset(seed=s)``, the following unseeded
    resets use s + 1, s + 2, ... and ``info["episode_seed"]`` says which seed an episode got.

    Episode k of a run is then reproducible on its own (re-create it with ``reset(seed=s + k)``),
    which is what makes collections resumable and evaluations comparable across worker
    counts. Before any seed is given, resets are unseeded and ``episode_seed`` is -1.
    """

    def __init__(self, env: gym.Env, seed: int | None = None) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, seed=seed)
        gym.Wrapper.__init__(self, env)
        self._next_seed = seed

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        if seed is not None:
            self._next_seed = seed
        episode_seed = self._next_seed
        if self._next_seed is not None:
            self._next_seed += 1
        observation, info = self.env.reset(seed=episode_seed, options=options)
        info["episode_seed"] = -1 if episode_seed is None else episode_seed
        return observation, info


class EndOnSuccess(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """End an episode (``terminated``) at the first step whose ``info["success"]`` is true.

    For evaluations that only count successes (success = succeeded at any step, the DP3/MP1
    convention): the verdict is the same as over the full episode, the remaining steps are
    not simulated, and returns cover the steps up to success only.
    """

    def __init__(self, env: gym.Env) -> None:
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.Wrapper.__init__(self, env)

    def step(self, action):
        observation, reward, terminated, truncated, info = self.env.step(action)
        return observation, reward, terminated or bool(info.get("success", False)), truncated, info
