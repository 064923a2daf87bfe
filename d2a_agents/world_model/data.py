"""World-model transitions from stored demonstrations: (V_t, past actions) -> V_{t+H}.

For every step t of an episode: the current cloud at t, the ``action_history`` actions
taken just before t (a_{t-K} .. a_{t-1}; steps before the episode start count as zero
actions, i.e. "the robot was still"), and the cloud at t + H, clamped to the episode's
last step. Windows never cross an episode boundary.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from collectors.dataset import episode_bounds
from d2a_agents.world_model.voxels import VoxelGrid


@dataclass(frozen=True)
class TransitionBatch:
    """Voxelised current and future clouds and the action history of a batch."""

    current: torch.Tensor  # (B, X, Y, Z) bool
    actions: torch.Tensor  # (B, K, A)
    target: torch.Tensor  # (B, X, Y, Z) bool


class WorldModelTransitions:
    """All transitions of the selected episodes of a frames TensorDict.

    Example:
        >>> transitions = WorldModelTransitions(dataset.frames(), grid, horizon=4, action_history=4)
        >>> batch = transitions.sample(8, torch.Generator().manual_seed(0))
        >>> batch.current.shape
        torch.Size([8, 64, 64, 16])
    """

    def __init__(
        self,
        frames: TensorDictBase,
        grid: VoxelGrid,
        horizon: int,
        action_history: int,
        episodes: Sequence[int] | None = None,
    ) -> None:
        ids, starts, lengths = episode_bounds(frames)
        if episodes is not None:
            unknown = set(episodes) - set(ids.tolist())
            if unknown:
                raise ValueError(f"unknown episode ids {sorted(unknown)}")
            keep = torch.isin(ids, torch.as_tensor(list(episodes)))
            ids, starts, lengths = ids[keep], starts[keep], lengths[keep]
        if ids.numel() == 0:
            raise ValueError("no episode selected")
        self.frames, self.grid = frames, grid
        self.episode_ids = ids
        rows, targets, history = [], [], []
        offsets = torch.arange(-action_history, 0)
        for start, length in zip(starts.tolist(), lengths.tolist(), strict=True):
            steps = torch.arange(length)
            rows.append(start + steps)
            targets.append(start + torch.clamp(steps + horizon, max=length - 1))
            past = steps[:, None] + offsets
            history.append(torch.where(past >= 0, start + past, -1))
        self.rows, self.targets, self.history = torch.cat(rows), torch.cat(targets), torch.cat(history)

    def __len__(self) -> int:
        return len(self.rows)

    def past_actions(self, indices: torch.Tensor) -> torch.Tensor:
        """Action histories (..., K, A) of the transitions at ``indices``; zeros before the episode start."""
        history = self.history[indices]
        actions = torch.as_tensor(self.frames["action"][history.clamp_min(0).reshape(-1)]).reshape(*history.shape, -1)
        return torch.where((history >= 0)[..., None], actions, torch.zeros_like(actions)).float()

    def get(self, indices: torch.Tensor) -> TransitionBatch:
        """The transitions at ``indices`` (positions in this table), voxelised."""
        clouds = torch.as_tensor(self.frames["point_cloud"][self.rows[indices]])
        futures = torch.as_tensor(self.frames["point_cloud"][self.targets[indices]])
        return TransitionBatch(current=self.grid.voxelize(clouds), actions=self.past_actions(indices),
                               target=self.grid.voxelize(futures))

    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> TransitionBatch:
        """A uniform draw (with replacement) of ``batch_size`` transitions."""
        return self.get(torch.randint(len(self), (batch_size,), generator=generator))
