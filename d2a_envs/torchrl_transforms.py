"""TorchRL transform that adds the D2A point cloud to any MuJoCo-backed environment.

It reads the same :class:`~d2a_envs.sensor.PointCloudSensor` as the Gymnasium wrapper
:class:`~d2a_envs.wrappers.PointCloudObservation`, so a plain simulator wrapped by TorchRL
(``GymWrapper``/``GymEnv``) gets the cloud a ``D2A-*`` Gymnasium id would give, without
going through the Gymnasium wrapper.
"""

from __future__ import annotations

import mujoco
import numpy as np
import torch
from tensordict import NestedKey, TensorDictBase
from torchrl.data import Bounded, Composite
from torchrl.envs import EnvBase, Transform

from d2a_envs.sensor import PointCloudConfig, PointCloudSensor
from d2a_envs.wrappers import point_cloud_space


def point_cloud_spec(config: PointCloudConfig, device: torch.device | None = None) -> Bounded:
    """TorchRL twin of :func:`~d2a_envs.wrappers.point_cloud_space`: float32, xyz bounded by the crop box."""
    space = point_cloud_space(config)
    return Bounded(
        low=torch.as_tensor(space.low),
        high=torch.as_tensor(space.high),
        shape=space.shape,
        dtype=torch.float32,
        device=device,
    )


def mujoco_model_data(env: EnvBase) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """The MuJoCo ``(model, data)`` behind a TorchRL env, or a ``TypeError`` saying why there is none.

    ``GymWrapper``/``GymEnv`` keep the Gymnasium env in ``_env``; its ``unwrapped`` env is
    where MuJoCo-based envs (Meta-World, gymnasium-robotics, D2A suite envs) hold them.
    """
    inner = getattr(env, "_env", env)
    simulator = getattr(inner, "unwrapped", inner)
    model = getattr(simulator, "model", None)
    data = getattr(simulator, "data", None)
    if not isinstance(model, mujoco.MjModel) or not isinstance(data, mujoco.MjData):
        raise TypeError(
            f"PointCloudTransform needs a MuJoCo simulator, but {type(env).__name__} wraps "
            f"{type(simulator).__name__}, whose `model`/`data` are {type(model).__name__}/"
            f"{type(data).__name__} instead of mujoco.MjModel/mujoco.MjData; wrap a MuJoCo "
            f"environment (e.g. GymWrapper(MetaWorldEnv('hammer-v3')))"
        )
    return model, data


class PointCloudTransform(Transform):
    """Write a fused, cropped, farthest-point-sampled point cloud on every reset and step.

    The cloud is read from the MuJoCo scene of the wrapped env (found through
    ``self.parent.base_env``), with the same sensor as the Gymnasium wrapper; it is
    float32 of shape ``(num_points, 3)``, or ``(num_points, 6)`` with RGB. When the crop
    holds fewer than ``num_points`` points, real points are repeated, drawn from the
    transform's own generator seeded with ``seed``. Only unbatched envs (batch size
    ``[]``) are supported: put the transform inside each worker of a batched env.

    Args:
        config: cameras, image size, point budget, crop box and depth backend.
        out_key: where the cloud is written in the tensordict.
        seed: seed of the generator used to fill sparse crops.

    Example:
        >>> from gymnasium.wrappers import TimeLimit
        >>> from torchrl.envs import GymWrapper, TransformedEnv
        >>> from d2a_envs import SUITE_DEFAULTS
        >>> from d2a_envs.suites.metaworld import MetaWorldEnv
        >>> base = GymWrapper(TimeLimit(MetaWorldEnv("hammer-v3"), 200))
        >>> env = TransformedEnv(base, PointCloudTransform(SUITE_DEFAULTS["metaworld"]))
        >>> env.reset()["point_cloud"].shape
        torch.Size([1024, 3])
    """

    def __init__(self, config: PointCloudConfig, out_key: NestedKey = "point_cloud", seed: int | None = None) -> None:
        super().__init__(in_keys=[], out_keys=[out_key])
        self.config = config
        self.sensor = PointCloudSensor(config)
        self.rng = np.random.default_rng(seed)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        """Read the scene as it is now and write the cloud (used by ``step`` via ``_step``)."""
        model, data = mujoco_model_data(self.parent.base_env)
        reading = self.sensor.read(model, data, self.rng)
        cloud = torch.from_numpy(reading.points).to(next_tensordict.device or torch.device("cpu"))
        next_tensordict.set(self.out_keys[0], cloud)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        """``_call`` is not run on reset by TorchRL, so the reset observation is filled here."""
        return self._call(tensordict_reset)

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        """Add the cloud's ``Bounded`` spec; fails early on a non-MuJoCo env, a missing camera or a batched env."""
        if observation_spec.shape != torch.Size([]):
            raise ValueError(
                f"PointCloudTransform supports unbatched envs only, got batch size {tuple(observation_spec.shape)}; "
                f"add the transform to each worker env instead"
            )
        model, _ = mujoco_model_data(self.parent.base_env)
        self.sensor.validate(model)
        observation_spec[self.out_keys[0]] = point_cloud_spec(self.config, observation_spec.device)
        return observation_spec

    def close(self) -> None:
        """Release the sensor's depth backend."""
        self.sensor.close()
