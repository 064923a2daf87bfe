"""D2A environments as TorchRL envs, with the per-step ``info`` entries the collectors need."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs import EnvBase, GymEnv, StepCounter, TransformedEnv
from torchrl.envs.gym_like import BaseInfoDictReader

import d2a_envs

# Key of the simulator state under TorchRL: GymWrapper renames a Dict entry "state" to "observation".
STATE_KEY = "observation"


class D2AInfoReader(BaseInfoDictReader):
    """Copy ``success`` (bool) and ``num_points_in_crop`` (int) from ``info`` into the tensordict.

    TorchRL's default reader expects numpy values; the D2A envs report plain Python ones.
    """

    def __init__(self) -> None:
        self._spec = Composite(
            success=Unbounded((), dtype=torch.bool), num_points_in_crop=Unbounded((), dtype=torch.int64), shape=[]
        )

    def __call__(self, info_dict: dict[str, Any], tensordict: TensorDictBase) -> TensorDictBase:
        for key, spec in self._spec.items():
            tensordict.set(key, torch.as_tensor(info_dict[key], dtype=spec.dtype))
        return tensordict

    @property
    def info_spec(self) -> Composite:
        return self._spec


def make_torchrl_env(task: str, env_kwargs: dict[str, Any] | None = None) -> EnvBase:
    """``GymEnv`` of a D2A task that also reports ``success`` and ``num_points_in_crop`` and
    counts steps (``step_count``).

    Example:
        >>> env = make_torchrl_env("hammer", {"num_points": 512})
        >>> env.rollout(3)["next", "success"].shape
        torch.Size([3])
    """
    spec = d2a_envs.get_task(task)
    env = GymEnv(spec.env_id, **(env_kwargs or {}))
    env.set_info_dict_reader(D2AInfoReader())
    return TransformedEnv(env, StepCounter())
