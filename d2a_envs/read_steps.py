"""Which steps of an episode a policy reads an observation at, so that an env can skip the rest.

A chunking policy plans every ``period`` steps (the first plan at the reset) from its last
``window`` observations, and executes the plan's actions in between: the observations of the
other steps are never read. In evaluation the expensive observations (a rendered cloud, an
imagined one, the simulator's look-ahead) are most of a step's cost, so the wrappers that make
them take a :class:`ReadSteps` and give :func:`unread_observation` (NaN) at the steps it skips.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from gymnasium import spaces


@dataclass(frozen=True)
class ReadSteps:
    """The steps whose observation a reader uses: step k (0 at the reset) is read when the next
    plan, at the first multiple of ``period`` at or after k, is fewer than ``window`` steps away.
    ``window`` 0 reads no step; the default reads every step.

    Example:
        >>> [k for k in range(8) if ReadSteps(period=3, window=2)(k)]
        [0, 2, 3, 5, 6]
    """

    period: int = 1
    window: int = 1

    def __post_init__(self) -> None:
        for name, least in (("period", 1), ("window", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or int(value) != value or value < least:
                raise ValueError(f"ReadSteps.{name} must be a whole number of at least {least}, not {value!r}")
            object.__setattr__(self, name, int(value))

    def __call__(self, step: int) -> bool:
        return self.window > 0 and (-step) % self.period < self.window

    def covers(self, other: ReadSteps) -> bool:
        """Whether every step ``other`` reads is read here too (both repeat within their periods'
        least common multiple, so that span decides)."""
        return all(self(step) for step in range(math.lcm(self.period, other.period)) if other(step))

    @classmethod
    def from_any(cls, value: ReadSteps | Sequence[int] | Mapping[str, int] | None) -> ReadSteps:
        """A :class:`ReadSteps` from itself, ``(period, window)``, ``{"period": .., "window": ..}``
        or ``None`` (every step)."""
        if value is None:
            return cls()
        if isinstance(value, cls):
            return value
        if isinstance(value, Mapping):
            return cls(**value)
        if isinstance(value, Sequence) and not isinstance(value, str) and len(value) == 2:
            return cls(*value)
        raise TypeError(f"read steps are a ReadSteps, (period, window) or a mapping of both, not {value!r}")


def unread_observation(space: spaces.Box) -> np.ndarray:
    """What an env gives at a step nobody reads: the space's shape, all NaN, so that a reader
    that does read it fails at once instead of acting on a made-up value."""
    return np.full(space.shape, np.nan, dtype=np.float32)
