"""Pen's sequence library: an expert whose action is a function of the target and the time.

Every Pen episode starts from the same state, and the target (a ghost pen with no contacts)
does not touch the dynamics: a sequence of actions that turns the pen to one target does so
in every episode with that target. The library holds one 200-step sequence per node of a grid
over the target's roll and pitch (the env draws both uniformly in [-1, 1] rad), made by
continuation (:mod:`benchmarks.pen_library`: each node starts from a solved neighbour's
sequence and is penalised for leaving it), so neighbouring sequences differ little. The
expert plays the sequence of the node nearest to its target, which still meets a target up
to half the grid's spacing away; the bilinear blend of the four nodes around the target
(``blend=True``) mixes sequences that each work into one that often does not (``d2a bench
pen-library`` checks both on the same seeded layouts). Same target, same step: same
action, unlike the planner, which finds a new way in every episode.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from collectors.atomic import atomic_savez

DEFAULT_LIBRARY = Path(__file__).parent / "data" / "adroit_pen_sequences.npz"
TARGET_RANGE = 1.0  # the env draws roll and pitch uniformly in [-1, 1] rad


def target_roll_pitch(quaternion: np.ndarray) -> tuple[float, float]:
    """Roll and pitch (rad) of the target's body quaternion (w, x, y, z), which the env sets from
    Euler angles (roll, pitch, 0) with gymnasium-robotics' ``euler2quat`` (whose rotation matrix
    R has R[1, 2] = -sin(roll) cos(pitch), R[2, 2] = cos(roll) cos(pitch), R[0, 2] = sin(pitch))."""
    w, x, y, z = np.asarray(quaternion, dtype=np.float64) / np.linalg.norm(quaternion)
    r12, r22, r02 = 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y), 2.0 * (x * z + w * y)
    return float(np.arctan2(-r12, r22)), float(np.arcsin(np.clip(r02, -1.0, 1.0)))


@dataclass(frozen=True)
class SequenceLibrary:
    """Normalised action sequences on a square grid of target angles.

    Attributes:
        axis: the grid's roll (and pitch) values, increasing and evenly spaced (n,).
        sequences: (n roll, n pitch, steps, actuators); NaN where a node is not solved yet.
        hold_steps: (n, n) steps at which each node's sequence meets its own target (the
            env's success), -1 where not solved: the build's record of weak nodes.
        attempts: (n, n) how many solved neighbours each node was optimised from.
    """

    axis: np.ndarray
    sequences: np.ndarray
    hold_steps: np.ndarray
    attempts: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.axis)
        if n < 2 or self.sequences.ndim != 4 or self.sequences.shape[:2] != (n, n):
            raise ValueError(f"sequences must be ({n}, {n}, steps, actuators) for a {n}-value axis, "
                             f"got {self.sequences.shape}")
        if not np.allclose(np.diff(self.axis), self.axis[1] - self.axis[0]) or self.axis[1] <= self.axis[0]:
            raise ValueError(f"the axis must be increasing and evenly spaced, got {self.axis}")
        if self.hold_steps.shape != (n, n) or self.attempts.shape != (n, n):
            raise ValueError(f"hold_steps and attempts must be ({n}, {n})")

    @classmethod
    def empty(cls, nodes: int, steps: int, actuators: int, extent: float = TARGET_RANGE) -> SequenceLibrary:
        return cls(np.linspace(-extent, extent, nodes), np.full((nodes, nodes, steps, actuators), np.nan),
                   np.full((nodes, nodes), -1), np.zeros((nodes, nodes), dtype=int))

    @classmethod
    def load(cls, path: str | Path) -> SequenceLibrary:
        with np.load(path) as stored:
            return cls(stored["axis"], stored["sequences"].astype(np.float64), stored["hold_steps"], stored["attempts"])

    def save(self, path: str | Path) -> None:
        """Write atomically (a build interrupted mid-write keeps the previous file). The
        sequences are stored as float32: round them so (:func:`as_stored`) before judging them."""
        atomic_savez(path, axis=self.axis, sequences=self.sequences.astype(np.float32), hold_steps=self.hold_steps,
                     attempts=self.attempts)

    @property
    def solved(self) -> np.ndarray:
        """(n, n) bool: the nodes that hold a sequence."""
        return ~np.isnan(self.sequences).any(axis=(2, 3))

    def action(self, roll: float, pitch: float, step: int, blend: bool = False) -> np.ndarray:
        """The action at ``step`` of the node nearest to (roll, pitch), or with ``blend`` the
        bilinear blend of the four nodes around it (the last step's action held after the
        sequence ends; angles outside the grid clamped to it)."""
        return self._at(roll, pitch, min(int(step), self.sequences.shape[2] - 1), blend)

    def sequence(self, roll: float, pitch: float, blend: bool = False) -> np.ndarray:
        """The whole sequence (steps, actuators) for (roll, pitch): every ``action`` at once."""
        return self._at(roll, pitch, slice(None), blend)

    def _at(self, roll: float, pitch: float, steps: int | slice, blend: bool) -> np.ndarray:
        if not self.solved.all():
            raise ValueError(f"the library has {int((~self.solved).sum())} unsolved nodes: finish its build")
        spacing, last = self.axis[1] - self.axis[0], len(self.axis) - 1
        position = np.clip((np.array([roll, pitch]) - self.axis[0]) / spacing, 0.0, last)
        if not blend:
            i, j = np.rint(position).astype(int)
            return self.sequences[i, j, steps]
        low = np.minimum(position.astype(int), last - 1)
        u, v = position - low
        i, j = low
        corners = self.sequences[i : i + 2, j : j + 2, steps]
        return ((1 - u) * (1 - v) * corners[0, 0] + (1 - u) * v * corners[0, 1]
                + u * (1 - v) * corners[1, 0] + u * v * corners[1, 1])


def as_stored(sequences: np.ndarray) -> np.ndarray:
    """``sequences`` as the library file holds them (float32): what an expert will replay."""
    return np.asarray(sequences, dtype=np.float32).astype(np.float64)


@lru_cache(maxsize=4)
def cached_library(path: str) -> SequenceLibrary:
    """The library at ``path``, read once per process."""
    if not Path(path).exists():
        raise FileNotFoundError(f"no Pen sequence library at {path}: build one with d2a bench pen-library")
    return SequenceLibrary.load(path)
