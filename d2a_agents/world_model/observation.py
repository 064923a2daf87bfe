"""Imagined point clouds: the world model's guess of the cloud H steps ahead, as an observation.

Both the Gymnasium wrapper :class:`ImaginationWrapper` and its TorchRL twin
:class:`ImaginationTransform` keep the last K actions (K = the world model's
``action_history``; zeros after a reset, i.e. "the robot was still", as in training) and
add ``imagined_point_cloud`` = ``imaginer(current cloud, last K actions)`` on every reset
and step. The action history follows the training data's convention: the observation at
step t comes with the actions a_{t-K} .. a_{t-1}, oldest first.

``gym.make("D2A-...", world_model=...)`` finds the wrapper through the ``d2a_envs.wrappers``
entry point that this package declares, so ``d2a_envs`` never imports ``d2a_agents``.
"""

from __future__ import annotations

import copy
import os
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from tensordict import NestedKey, TensorDictBase
from torchrl.data import Bounded, Composite
from torchrl.envs import Transform

from d2a_agents.checkpoint import CheckpointError
from d2a_agents.world_model.imagine import Imaginer
from d2a_envs.read_steps import ReadSteps, unread_observation
from d2a_envs.sampling import CropBox
from d2a_envs.wrappers import IMAGINED_KEY, PointCloudObservation

__all__ = ["IMAGINED_KEY", "ImaginationTransform", "ImaginationWrapper", "check_world_model", "load_imaginer"]
# Crop boxes read back from float32 spaces/specs differ from the float64 box of a
# checkpoint by rounding only; anything above this is a real mismatch.
_BOX_TOLERANCE = 1e-5


def load_imaginer(
    world_model: Imaginer | str | os.PathLike, num_points: int, seed: int = 0, output: str = "future"
) -> Imaginer:
    """An :class:`~d2a_agents.world_model.imagine.Imaginer` of ``num_points`` points owned by the caller.

    A checkpoint path is loaded (``CheckpointError`` for a missing, foreign or non-world-model
    file); an ``Imaginer`` is shallow-copied (the network is shared, read-only) so that its
    point count, ``output`` and generator can be set without touching the caller's object.
    """
    if isinstance(world_model, Imaginer):
        imaginer = copy.copy(world_model)
        imaginer.num_points = int(num_points)
        imaginer.output = output
        imaginer.rng = np.random.default_rng(seed)
        return imaginer
    if isinstance(world_model, (str, os.PathLike)):
        return Imaginer.from_checkpoint(Path(world_model), num_points=int(num_points), seed=seed, output=output)
    raise TypeError(f"world_model must be an Imaginer or a checkpoint path, got {type(world_model).__name__}")


def check_world_model(imaginer: Imaginer, crop_box: CropBox, action_dim: int, source: str = "the world model") -> None:
    """Refuse a world model whose voxel box or action size differs from the env's.

    Boxes equal up to float32 rounding count as equal. Raises
    :class:`~d2a_agents.checkpoint.CheckpointError` naming ``source`` on a mismatch.
    """
    grid_box = imaginer.grid.box
    close = np.allclose(crop_box.low, grid_box.low, rtol=0, atol=_BOX_TOLERANCE) and np.allclose(
        crop_box.high, grid_box.high, rtol=0, atol=_BOX_TOLERANCE
    )
    try:
        imaginer.check_compatible(grid_box if close else crop_box, int(action_dim))
    except CheckpointError as error:
        raise CheckpointError(
            f"{source} does not fit this env: {error}; train a world model on data collected with "
            f"the env's crop box and action space, or make the env with the box the model was trained on"
        ) from error


def imagined_cloud_space(crop_box: CropBox, num_points: int) -> spaces.Box:
    """Box space of an imagined (num_points, 3) float32 cloud: xyz inside the crop box."""
    shape = (int(num_points), 3)
    low = np.broadcast_to(np.asarray(crop_box.low, dtype=np.float32), shape)
    high = np.broadcast_to(np.asarray(crop_box.high, dtype=np.float32), shape)
    return spaces.Box(low, high, shape, np.float32)


def _describe(world_model: object) -> str:
    return f"world model {world_model}" if isinstance(world_model, (str, os.PathLike)) else "the world model"


def _point_cloud_wrapper(env: gym.Env) -> PointCloudObservation | None:
    """The :class:`PointCloudObservation` in ``env``'s wrapper chain (outermost first), if any."""
    current: Any = env
    while current is not None:
        if isinstance(current, PointCloudObservation):
            return current
        current = getattr(current, "env", None)
    return None


class ImaginationWrapper(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Add ``imagined_point_cloud`` (N x 3 float32, N = the env's point count unless given) to a D2A env.

    The env's observation must be a ``Dict`` with ``point_cloud`` (any ``D2A-*`` env, or a
    :class:`~d2a_envs.wrappers.PointCloudObservation`). The world model must have been
    trained with the env's crop box and action size, and on ``task`` when it is given (the
    ``D2A-*`` ids give it); a mismatch raises :class:`~d2a_agents.checkpoint.CheckpointError`
    here, not at the first step.

    When the model predicts fewer occupied voxels than N, points are repeated, drawn from
    the wrapper's generator: it is seeded with ``seed`` and re-seeded by ``reset(seed=s)``,
    so seeded episodes reproduce their imagined clouds.

    Args:
        env: the env whose observation holds ``point_cloud``.
        world_model: an :class:`~d2a_agents.world_model.imagine.Imaginer` or a checkpoint
            path written by ``d2a train-wm``.
        seed: seed of the fill generator until a seeded reset.
        task: the env's task, checked against the tasks the world model was trained on.
        num_points: points of the imagined cloud; default: those of the env's cloud.
        output: what the imagined cloud holds, "future" or "change" (see
            :class:`~d2a_agents.world_model.imagine.Imaginer`).
        read_steps: the steps whose imagined cloud is read
            (:class:`~d2a_envs.read_steps.ReadSteps`; default every step): the others are not
            imagined and hold NaN (the action history still takes every action).

    Example:
        >>> env = gym.make("D2A-MetaWorld-Hammer-v0", world_model="runs/hammer/wm.pt")
        >>> obs, info = env.reset(seed=0)
        >>> obs["imagined_point_cloud"].shape
        (1024, 3)
    """

    def __init__(
        self, env: gym.Env, world_model: Imaginer | str | os.PathLike, seed: int = 0, task: str | None = None,
        num_points: int | None = None, output: str = "future", read_steps: ReadSteps | None = None,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(self, world_model=world_model, seed=seed, task=task,
                                                 num_points=num_points, output=output, read_steps=read_steps)
        gym.Wrapper.__init__(self, env)
        space = env.observation_space
        if not isinstance(space, spaces.Dict) or "point_cloud" not in space.spaces:
            raise TypeError(f"ImaginationWrapper needs a Dict observation space with 'point_cloud', got {space}")
        if not isinstance(env.action_space, spaces.Box) or len(env.action_space.shape) != 1:
            raise TypeError(f"ImaginationWrapper needs a flat Box action space, got {env.action_space}")
        cloud_space = space.spaces["point_cloud"]
        maker = _point_cloud_wrapper(env)
        if maker is not None:
            crop_box = maker.config.crop_box
        else:  # a cloud made elsewhere: its space's bounds are the box
            crop_box = CropBox(tuple(cloud_space.low[0, :3]), tuple(cloud_space.high[0, :3]))
        num_points = int(cloud_space.shape[0] if num_points is None else num_points)
        if num_points < 1:
            raise ValueError(f"the imagined cloud needs at least 1 point, not {num_points}")
        self.imaginer = load_imaginer(world_model, num_points, seed, output)
        check_world_model(self.imaginer, crop_box, env.action_space.shape[0], _describe(world_model))
        if task is not None and self.imaginer.tasks and task not in self.imaginer.tasks:
            raise CheckpointError(f"{_describe(world_model)} was trained on {list(self.imaginer.tasks)}, "
                                  f"not on {task}: it cannot imagine this scene")
        self.crop_box = crop_box
        self.history_length = self.imaginer.config.action_history
        self.action_dim = self.imaginer.config.action_dim
        self._history = np.zeros((self.history_length, self.action_dim), dtype=np.float32)
        self.read_steps = ReadSteps.from_any(read_steps)
        self._step = 0
        self.observation_space = spaces.Dict(
            {**space.spaces, IMAGINED_KEY: imagined_cloud_space(self.imaginer.grid.box, num_points)}
        )

    @property
    def action_history(self) -> np.ndarray:
        """The last K actions, oldest first (a copy): what the next imagination is conditioned on."""
        return self._history.copy()

    def _imagine(self, observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not self.read_steps(self._step):
            return {**observation, IMAGINED_KEY: unread_observation(self.observation_space[IMAGINED_KEY])}
        imagined = self.imaginer(observation["point_cloud"], self._history)
        return {**observation, IMAGINED_KEY: imagined}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        observation, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self.imaginer.rng = np.random.default_rng(seed)
        self._history = np.zeros_like(self._history)
        self._step = 0
        return self._imagine(observation), info

    def step(self, action: np.ndarray):
        observation, reward, terminated, truncated, info = self.env.step(action)
        taken = np.asarray(action, dtype=np.float32).reshape(self.action_dim)
        self._history = np.concatenate([self._history[1:], taken[None]], axis=0)
        self._step += 1
        return self._imagine(observation), reward, terminated, truncated, info


class ImaginationTransform(Transform):
    """TorchRL twin of :class:`ImaginationWrapper`: writes ``imagined_point_cloud`` on reset and step.

    Reads the cloud (``cloud_key``, written by the env or by an earlier
    :class:`~d2a_envs.torchrl_transforms.PointCloudTransform`) and, at each step, the action
    of the root tensordict (``action_key``), which enters the action history before the
    imagined cloud of the next observation is computed. Only unbatched envs (batch size
    ``[]``) are supported: put the transform inside each worker of a batched env.

    The crop box is read from the cloud's ``Bounded`` spec unless ``crop_box`` is given; it
    and the action size must match the world model's (``CheckpointError`` otherwise, raised
    when the spec is first built). Fill points (when the model predicts fewer occupied
    voxels than N) come from the transform's own generator seeded with ``seed``.

    Args:
        world_model: an ``Imaginer`` or a world-model checkpoint path.
        cloud_key: where the current point cloud is read.
        action_key: where the action is read.
        out_key: where the imagined cloud is written.
        num_points: points of the imagined cloud; default: those of the current cloud.
        crop_box: the env's crop box, when the cloud spec does not carry it.
        seed: seed of the fill generator.
        output: what the imagined cloud holds, "future" or "change".

    Example:
        >>> base = GymWrapper(gym.make("D2A-MetaWorld-Hammer-v0"))
        >>> env = TransformedEnv(base, ImaginationTransform("runs/hammer/wm.pt"))
        >>> env.rollout(3)["next", "imagined_point_cloud"].shape
        torch.Size([3, 1024, 3])
    """

    def __init__(
        self,
        world_model: Imaginer | str | os.PathLike,
        cloud_key: NestedKey = "point_cloud",
        action_key: NestedKey = "action",
        out_key: NestedKey = IMAGINED_KEY,
        num_points: int | None = None,
        crop_box: CropBox | None = None,
        seed: int = 0,
        output: str = "future",
    ) -> None:
        super().__init__(in_keys=[cloud_key, action_key], out_keys=[out_key])
        if isinstance(world_model, (str, os.PathLike)):  # load once, fail early on a bad file
            world_model = Imaginer.from_checkpoint(Path(world_model), num_points=num_points, output=output)
        elif not isinstance(world_model, Imaginer):
            raise TypeError(f"world_model must be an Imaginer or a checkpoint path, got {type(world_model).__name__}")
        self._source = world_model
        self.imaginer: Imaginer | None = None  # made once the cloud spec (hence N) is known
        self._num_points = num_points
        self._crop_box = crop_box
        self._seed = seed
        self._output = output
        self.history = torch.zeros(world_model.config.action_history, world_model.config.action_dim)

    @property
    def cloud_key(self) -> NestedKey:
        return self.in_keys[0]

    @property
    def action_key(self) -> NestedKey:
        return self.in_keys[1]

    def _setup(self, observation_spec: Composite) -> Bounded:
        """Check the env against the world model, make the owned imaginer, return the output spec."""
        if observation_spec.shape != torch.Size([]):
            raise ValueError(
                f"ImaginationTransform supports unbatched envs only, got batch size {tuple(observation_spec.shape)}; "
                f"add the transform to each worker env instead"
            )
        cloud_spec = observation_spec.get(self.cloud_key, None)
        if cloud_spec is None:
            raise KeyError(f"ImaginationTransform reads {self.cloud_key!r}, which the env does not observe")
        box = self._crop_box
        if box is None:
            if not isinstance(cloud_spec, Bounded):
                raise TypeError(
                    f"the spec of {self.cloud_key!r} is {type(cloud_spec).__name__}, not Bounded: pass crop_box="
                )
            low, high = cloud_spec.space.low, cloud_spec.space.high
            box = CropBox(tuple(low[0, :3].tolist()), tuple(high[0, :3].tolist()))
        action_spec = self.parent.full_action_spec[self.action_key]
        num_points = self._num_points or int(cloud_spec.shape[-2])
        if self.imaginer is None or self.imaginer.num_points != num_points:
            self.imaginer = load_imaginer(self._source, num_points, self._seed, self._output)
        check_world_model(self.imaginer, box, int(action_spec.shape[-1]), "the world model")
        grid_box = self.imaginer.grid.box
        shape = torch.Size([num_points, 3])
        return Bounded(
            low=torch.tensor(grid_box.low, dtype=torch.float32).expand(shape).clone(),
            high=torch.tensor(grid_box.high, dtype=torch.float32).expand(shape).clone(),
            shape=shape,
            dtype=torch.float32,
            device=observation_spec.device,
        )

    def transform_observation_spec(self, observation_spec: Composite) -> Composite:
        """Add the imagined cloud's ``Bounded`` float32 spec (after checking the world model fits)."""
        observation_spec[self.out_keys[0]] = self._setup(observation_spec)
        return observation_spec

    def _write(self, tensordict: TensorDictBase) -> TensorDictBase:
        if self.imaginer is None:
            self._setup(self.parent.observation_spec)
        cloud = tensordict.get(self.cloud_key)
        imagined = self.imaginer(cloud.detach().cpu().numpy(), self.history.numpy())
        tensordict.set(self.out_keys[0], torch.from_numpy(imagined).to(cloud.device))
        return tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        """New episode: the robot was still (zero history); imagine from the reset cloud."""
        self.history = torch.zeros_like(self.history)
        return self._write(tensordict_reset)

    def _reset_on_native_autoreset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._reset(tensordict, tensordict_reset)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        """Append the action just taken (root tensordict), then imagine from the next cloud."""
        action = tensordict.get(self.action_key).detach().to("cpu", torch.float32).reshape(-1)
        if action.numel() != self.history.shape[1]:
            raise ValueError(f"expected a {self.history.shape[1]}-d action, got shape {tuple(action.shape)}")
        self.history = torch.cat([self.history[1:], action[None]], dim=0)
        return self._write(next_tensordict)

    def _call(self, next_tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError("ImaginationTransform needs the action of each step: use it inside a TransformedEnv")

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        raise NotImplementedError(
            "ImaginationTransform keeps a per-episode action history and only runs inside a TransformedEnv"
        )
