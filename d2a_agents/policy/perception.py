"""Does the policy look? One-step error with each input intact or shuffled across windows.

A policy that ignores its point cloud predicts the same actions when the clouds of a batch
are permuted among its windows; one that reads them gets worse. :func:`reliance` measures
the one-step error (normalized action MSE, the same noise in every pass) on a fixed set of
windows: intact, with the clouds (current and imagined together; a 2D policy's images) shuffled, with the
imagined cloud alone shuffled (policies with a second cloud encoder), and with the
low-dimensional observation (``agent_pos`` or ``state``) shuffled. The ratio
shuffled / intact per input is the policy's reliance on it: about 1 means the input is
ignored.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from d2a_agents.policy.agent import CLOUD_KEYS, IMAGINED_KEY, Policy
from d2a_envs.wrappers import IMAGE_KEY


@dataclass(frozen=True)
class Reliance:
    """One-step errors (normalized action MSE) on the same windows, intact and with one input shuffled."""

    windows: int
    intact: float
    clouds_shuffled: float | None  # None: the policy reads no cloud (nor image)
    state_shuffled: float
    imagined_shuffled: float | None = None  # None: no second cloud encoder
    perceives: str = "clouds"  # what clouds_shuffled shuffled: "clouds", or a 2D policy's "images"

    @classmethod
    def from_record(cls, record: dict[str, float | int | str | None]) -> Reliance:
        """A check as the training checkpoint stores it (its fields plus ``step`` and ``where``)."""
        return cls(**{key: value for key, value in record.items() if key not in ("step", "where")})

    @property
    def cloud_ratio(self) -> float | None:
        return None if self.clouds_shuffled is None else self.clouds_shuffled / max(self.intact, 1e-12)

    @property
    def state_ratio(self) -> float:
        return self.state_shuffled / max(self.intact, 1e-12)

    @property
    def imagined_ratio(self) -> float | None:
        return None if self.imagined_shuffled is None else self.imagined_shuffled / max(self.intact, 1e-12)

    def summary(self, where: str) -> str:
        cloud = "no cloud" if self.cloud_ratio is None else f"{self.perceives} shuffled {self.clouds_shuffled:.4f} " \
                                                             f"(x{self.cloud_ratio:.1f})"
        if self.imagined_ratio is not None:
            cloud += f", imagined alone {self.imagined_shuffled:.4f} (x{self.imagined_ratio:.1f})"
        return (f"one-step error on {self.windows} {where} windows: intact {self.intact:.4f}, {cloud}, "
                f"state shuffled {self.state_shuffled:.4f} (x{self.state_ratio:.1f})")


def _error(policy: Policy, observation: dict[str, torch.Tensor], target: torch.Tensor, seed: int) -> float:
    generator = torch.Generator(device=target.device).manual_seed(seed)
    prediction = policy.sample_normalized(observation, generator)
    return (prediction - target).pow(2).mean().item()


@torch.no_grad()
def reliance(
    policy: Policy, observation: dict[str, torch.Tensor], actions: torch.Tensor, seed: int = 0
) -> Reliance:
    """The policy's one-step errors on a batch of raw windows (``observation`` keyed like
    ``policy.config.observation_keys``, ``actions`` (B, horizon, A) in env units), intact and
    with the clouds or the low-dimensional observation permuted across the batch (a fixed
    derangement: every window gets another window's input)."""
    batch = actions.shape[0]
    if batch < 2:
        raise ValueError("reliance needs at least 2 windows to shuffle")
    was_training = policy.training
    policy.eval()
    target = policy.normalizers["action"].normalize(actions)
    second = policy.config.encoder.use_imagination
    if second and IMAGINED_KEY not in observation:  # d2a-present: its second input is the current cloud
        observation = {**observation, IMAGINED_KEY: observation["point_cloud"]}
    shift = torch.roll(torch.arange(batch, device=actions.device), batch // 2)  # a derangement for any batch >= 2

    def shuffled(keys: tuple[str, ...]) -> dict[str, torch.Tensor]:
        return {key: value[shift] if key in keys else value for key, value in observation.items()}

    intact = _error(policy, observation, target, seed)
    cloud_keys = tuple(key for key in observation if key in (*CLOUD_KEYS, IMAGE_KEY))
    clouds = _error(policy, shuffled(cloud_keys), target, seed) if cloud_keys else None
    state = _error(policy, shuffled((policy.config.encoder.state_key,)), target, seed)
    imagined = _error(policy, shuffled((IMAGINED_KEY,)), target, seed) if second else None
    policy.train(was_training)
    perceives = "images" if IMAGE_KEY in cloud_keys else "clouds"
    return Reliance(batch, intact, clouds, state, imagined, perceives)
