"""Policy-training windows over stored demonstrations, and the min/max normalizer policies use.

A window follows the Diffusion Policy / DP3 convention. For a *current* step ``t`` of an
episode it holds ``n_obs_steps`` observations and ``horizon`` actions, both starting at
``t - (n_obs_steps - 1)``. Windows never cross an episode boundary: rows before the episode's
first step repeat its first frame, rows after its last step repeat its last frame
(DP3's ``pad_before = n_obs_steps - 1``, ``pad_after = n_action_steps - 1``). The windows are
DP3's, less any whose current step would itself be padding, so with MP1's defaults
(horizon 4, 2 observations, 4 executed actions) every step of every episode is the current
step of exactly one window. When ``horizon - n_obs_steps > n_action_steps - 1`` (DP3's
16/2/8), the last ``horizon - n_obs_steps - (n_action_steps - 1)`` steps of each episode are
not current steps, as in DP3, and an episode no longer than that yields no window.

Sampling does not use TorchRL's ``SliceSampler``: in torchrl 0.14.1 it cannot produce these
windows (checked by hand on episodes of 5, 1 and 7 steps). Its ``pad_output`` pads only at the
end of a slice, by repeating the last real step, so a window that begins before the episode is
shifted instead of repeating the first frame in front. It also picks a trajectory first and
then a start inside it, which over-weights the steps of short episodes against DP3's uniform
draw over windows. And an integer ``span`` with ``strict_length=False`` raises a RuntimeError
once an episode is shorter than ``slice_len``. Instead, the window table (storage rows of each
window, clamped to its episode) is built once with vectorised torch ops and sampled with a
seeded ``torch.Generator``. What TorchRL still provides is the storage: ``DemoDataset.frames()``
is the ``LazyMemmapStorage``'s memory-mapped TensorDict, and windows are gathered from it
without loading the whole data set.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torch.utils.data import Dataset

RANGE_EPS = 1e-4  # dimensions whose data range is below this are treated as constant (DP3's range_eps)


@dataclass(frozen=True)
class WindowConfig:
    """How windows are cut (defaults are MP1's; DP3 uses horizon 16, 2 observations, 8 actions)."""

    horizon: int = 4  # actions per window, starting with the oldest observation's step
    n_obs_steps: int = 2  # observations per window, ending at the current step
    n_action_steps: int = 4  # actions the policy executes; sets how far a window may run past the end
    obs_keys: tuple[str, ...] = ("point_cloud", "agent_pos")
    action_key: str = "action"

    def __post_init__(self) -> None:
        for name in ("horizon", "n_obs_steps", "n_action_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"WindowConfig.{name} must be at least 1, not {getattr(self, name)}")
        if not self.obs_keys:
            raise ValueError("WindowConfig.obs_keys must name at least one observation key")

    @property
    def pad_before(self) -> int:
        """Steps a window may start before its episode (padded with the first frame)."""
        return self.n_obs_steps - 1

    @property
    def pad_after(self) -> int:
        """Steps a window's actions may run past its episode (padded with the last frame)."""
        return self.n_action_steps - 1


def _require_finite(name: str, data: torch.Tensor) -> None:
    if data.is_floating_point() and not bool(torch.isfinite(data).all()):
        raise ValueError(f"{name} holds NaN or inf values")


class Normalizer(nn.Module):
    """Per-dimension affine map of data onto [-1, 1] from its min and max.

    Dimensions whose range is below ``range_eps`` are only centred (scale 1), so a constant
    dimension maps to exactly 0 and back to exactly its value. A module whose statistics are
    buffers: inside a policy they belong to its state dict, so a checkpoint carries them.

    Example:
        >>> normalizer = Normalizer.fit(torch.tensor([[0.0, 5.0], [2.0, 5.0]]))
        >>> normalizer.normalize(torch.tensor([1.0, 5.0]))
        tensor([0., 0.])
        >>> normalizer.unnormalize(torch.tensor([1.0, 0.0]))
        tensor([2., 5.])
    """

    def __init__(self, low: torch.Tensor, high: torch.Tensor, range_eps: float = RANGE_EPS) -> None:
        super().__init__()
        if low.shape != high.shape:
            raise ValueError(f"low {tuple(low.shape)} and high {tuple(high.shape)} differ in shape")
        _require_finite("normalizer low", low)
        _require_finite("normalizer high", high)
        if bool((high < low).any()):
            raise ValueError("normalizer high lies below low")
        if not range_eps > 0:
            raise ValueError(f"range_eps must be positive, not {range_eps}")
        low, high = low.to(torch.float64), high.to(torch.float64)
        half_range = (high - low) / 2
        self.register_buffer("low", low)
        self.register_buffer("high", high)
        self.register_buffer("centre", low + half_range)
        self.register_buffer("half_range", torch.where(2 * half_range < range_eps, torch.ones_like(half_range),
                                                       half_range))

    @classmethod
    def fit(cls, data: torch.Tensor, range_eps: float = RANGE_EPS) -> Normalizer:
        """Statistics of ``data`` over its first dimension (rows), one per remaining dimension."""
        data = torch.as_tensor(data)
        if data.ndim < 1 or data.shape[0] == 0:
            raise ValueError(f"cannot fit a normalizer to data of shape {tuple(data.shape)}")
        _require_finite("normalizer data", data)
        return cls(data.amin(0), data.amax(0), range_eps)

    @classmethod
    def placeholder(cls, *shape: int) -> Normalizer:
        """The identity map of that shape, to be overwritten by ``load_state_dict``."""
        return cls(-torch.ones(shape), torch.ones(shape))

    @property
    def shape(self) -> torch.Size:
        return self.low.shape

    def _check(self, x: torch.Tensor) -> None:
        if x.ndim < len(self.shape) or x.shape[x.ndim - len(self.shape) :] != self.shape:
            raise ValueError(f"expected data ending in shape {tuple(self.shape)}, got {tuple(x.shape)}")
        _require_finite("data to (un)normalize", x)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """Map ``x`` (any leading dims) onto [-1, 1]; the data it was fitted to lands exactly there."""
        self._check(x)
        return (x - self.centre.to(x)) / self.half_range.to(x)

    def unnormalize(self, y: torch.Tensor) -> torch.Tensor:
        """Inverse of :meth:`normalize` (e.g. to turn predicted actions back into env actions)."""
        self._check(y)
        return y * self.half_range.to(y) + self.centre.to(y)


def episode_bounds(frames: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(ids, starts, lengths)`` of the episodes in ``frames``, in storage order (CPU tensors,
    wherever ``frames`` lives).

    Each episode must occupy one contiguous run of rows, as :class:`~collectors.storage.DemoDataset`
    stores them.
    """
    if "episode" not in frames.keys():
        raise ValueError("frames lack the 'episode' key that tells episodes apart")
    episode = torch.as_tensor(frames["episode"]).reshape(-1).cpu()  # bookkeeping stays on the CPU
    ids, lengths = torch.unique_consecutive(episode, return_counts=True)
    if ids.unique().numel() != ids.numel():
        raise ValueError("an episode id occurs in more than one run of rows: episodes must be contiguous")
    return ids, lengths.cumsum(0) - lengths, lengths


def future_rows(frames: TensorDictBase, horizon: int) -> torch.Tensor:
    """For every row of ``frames``, the row ``horizon`` steps later in its episode (the
    episode's last row where it ends sooner)."""
    _, starts, lengths = episode_bounds(frames)
    offsets = torch.cat([torch.arange(int(length)) for length in lengths])
    first = torch.repeat_interleave(starts, lengths)
    last = torch.repeat_interleave(starts + lengths - 1, lengths)
    return torch.minimum(first + offsets + horizon, last)


class DemoWindows(Dataset):
    """Every policy-training window of the chosen episodes of ``frames``.

    ``frames`` is a TensorDict of steps in storage order (``DemoDataset.frames()`` or one built
    by hand) holding ``episode`` and the configured keys. An item has ``obs/<key>`` of shape
    ``(n_obs_steps, ...)``, ``action`` of shape ``(horizon, A)``, and the ``episode`` id and
    ``step`` of its current step. Windows hold raw values: the policy normalizes them.

    Example:
        >>> frames = DemoDataset.open("data/hammer").frames()
        >>> held_out = [0, 1]
        >>> train = [i for i in episode_bounds(frames)[0].tolist() if i not in held_out]
        >>> windows = DemoWindows(frames, WindowConfig(), episodes=train)
        >>> batch = windows.sample(256, torch.Generator().manual_seed(0))
        >>> batch["obs", "point_cloud"].shape, batch["action"].shape
        (torch.Size([256, 2, 1024, 3]), torch.Size([256, 4, 4]))
        >>> loader = DataLoader(windows, batch_size=256, shuffle=True, collate_fn=torch.stack)
    """

    def __init__(
        self,
        frames: TensorDictBase,
        config: WindowConfig | None = None,
        episodes: Sequence[int] | None = None,
    ) -> None:
        self.config = config = config or WindowConfig()
        keys = (*config.obs_keys, config.action_key)
        missing = [key for key in keys if key not in frames.keys()]
        if missing:
            raise ValueError(f"frames lack {missing}")
        self.frames = frames

        ids, starts, lengths = episode_bounds(frames)
        if episodes is None:
            chosen = torch.ones_like(ids, dtype=torch.bool)
        else:
            wanted = torch.as_tensor(list(episodes), dtype=ids.dtype)
            unknown = wanted[~torch.isin(wanted, ids)]
            if unknown.numel():
                raise ValueError(f"episodes {unknown.tolist()} are not in frames")
            chosen = torch.isin(ids, wanted)
        self.episode_ids = ids[chosen]

        run = torch.repeat_interleave(torch.arange(ids.numel()), lengths)  # episode run of every row
        first, last = starts[run], starts[run] + lengths[run] - 1
        step = torch.arange(run.numel()) - first
        overrun = max(0, config.horizon - config.n_obs_steps - config.pad_after)  # steps that cannot be current
        current = torch.nonzero(chosen[run] & (step <= lengths[run] - 1 - overrun)).squeeze(1)
        if current.numel() == 0:
            raise ValueError("no windows: no chosen episode is long enough for this WindowConfig")
        lo, hi = first[current, None], last[current, None]
        start = current[:, None] - config.pad_before
        device = frames["episode"].device  # the row tables live with the frames they index
        self.obs_rows = (start + torch.arange(config.n_obs_steps)).clamp(lo, hi).to(device)
        self.action_rows = (start + torch.arange(config.horizon)).clamp(lo, hi).to(device)
        self.current_rows = current.to(device)
        self.steps = step[current].to(device)

    def __len__(self) -> int:
        return self.current_rows.numel()

    def _read(self, key: str, rows: torch.Tensor) -> torch.Tensor:
        return self.frames[key][rows]

    def get(self, indices: torch.Tensor) -> TensorDict:
        """The windows at ``indices`` (1-d), stacked along a leading batch dimension."""
        indices = torch.as_tensor(indices, dtype=torch.int64).to(self.current_rows.device)
        return TensorDict(
            {
                "obs": {key: self._read(key, self.obs_rows[indices]) for key in self.config.obs_keys},
                "action": self._read(self.config.action_key, self.action_rows[indices]),
                "episode": self.frames["episode"][self.current_rows[indices]],
                "step": self.steps[indices],
            },
            batch_size=indices.shape,
        )

    def __getitem__(self, index: int) -> TensorDict:
        if not -len(self) <= index < len(self):
            raise IndexError(f"window {index} out of range for {len(self)} windows")
        return self.get(torch.tensor([index]))[0]

    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> TensorDict:
        """``batch_size`` windows drawn uniformly with replacement (reproducible for a seeded ``generator``)."""
        device = generator.device if generator is not None else None  # a CUDA generator draws on the GPU
        return self.get(torch.randint(len(self), (batch_size,), generator=generator, device=device))
