"""D2A environments as TorchRL envs, with the per-step ``info`` entries the collectors need."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import EnvBase, GymWrapper, StepCounter, TransformedEnv
from torchrl.envs.gym_like import BaseInfoDictReader

import d2a_envs
from collectors.expert_future import ExpertFuture
from d2a_envs.factory import observation_read_steps
from d2a_envs.wrappers import EndOnSuccess, SeedEachReset

# Key of the simulator state under TorchRL: GymWrapper renames a Dict entry "state" to "observation".
STATE_KEY = "observation"
# An env option of make_torchrl_env only (gym.make has no simulator look-ahead): the keyword
# arguments of :class:`~collectors.expert_future.ExpertFuture`, the true future cloud.
EXPERT_FUTURE_KEY = "expert_future"


class D2AInfoReader(BaseInfoDictReader):
    """Copy ``success`` (bool), ``num_points_in_crop`` and ``episode_seed`` (int) from ``info``
    into the tensordict (``episode_seed`` is only in reset infos: steps carry it forward).

    TorchRL's default reader expects numpy values; the D2A envs report plain Python ones.
    """

    def __init__(self) -> None:
        self._spec = Composite(
            success=Unbounded((), dtype=torch.bool),
            num_points_in_crop=Unbounded((), dtype=torch.int64),
            episode_seed=Unbounded((), dtype=torch.int64),
            shape=[],
        )
        self._episode_seed = -1

    def __call__(self, info_dict: dict[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        self._episode_seed = info_dict.get("episode_seed", self._episode_seed)
        values = {**info_dict, "episode_seed": self._episode_seed}
        for key, spec in self._spec.items():
            tensordict.set(key, torch.as_tensor(values[key], dtype=spec.dtype))
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._spec


def make_torchrl_env(
    task: str, env_kwargs: dict[str, Any] | None = None, seed: int | None = None, end_on_success: bool = False
) -> EnvBase:
    """TorchRL env of a D2A task that reports ``success``, ``num_points_in_crop`` and
    ``episode_seed`` and counts steps (``step_count``); with ``end_on_success``, episodes
    terminate at their first success (:class:`~d2a_envs.wrappers.EndOnSuccess`).

    Every episode gets its own seed (:class:`~d2a_envs.wrappers.SeedEachReset`): with
    ``seed=s`` the episodes use s, s + 1, ... whatever collector drives the env, and each
    step carries its episode's seed in ``episode_seed``. ``env_kwargs`` go to ``gym.make``, less
    :data:`EXPERT_FUTURE_KEY`, whose dict (``horizon``, ``num_points``, ``stacked_horizons``) adds
    the expert's true future cloud (:class:`~collectors.expert_future.ExpertFuture`), looked up at
    the steps ``read_steps`` gives ``imagined_point_cloud`` (:func:`d2a_envs.make_env`).

    Example:
        >>> env = make_torchrl_env("hammer", {"num_points": 512})
        >>> env.rollout(3)["next", "success"].shape
        torch.Size([3])
    """
    spec = d2a_envs.get_task(task)
    env_kwargs = dict(env_kwargs or {})
    future = env_kwargs.pop(EXPERT_FUTURE_KEY, None)
    # Gymnasium's checker would take the NaN of a step that read_steps skips for a broken observation.
    env = gym.make(spec.env_id, disable_env_checker="read_steps" in env_kwargs, **env_kwargs)
    if future is not None:
        imagined_steps = observation_read_steps(env_kwargs.get("read_steps"))[1]
        env = ExpertFuture(env, **future, read_steps=imagined_steps)
    env = GymWrapper(SeedEachReset(EndOnSuccess(env) if end_on_success else env, seed=seed))
    env.set_info_dict_reader(D2AInfoReader())
    return TransformedEnv(env, StepCounter())
