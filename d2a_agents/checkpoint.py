"""Checkpoints that carry their configuration, so that a mismatched use is refused clearly."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import torch

from collectors.atomic import atomic_torch_save

FORMAT = "d2a-checkpoint"
# v2: trained on clouds that show the goal markers (data-set format v2).
FORMAT_VERSION = 2


class CheckpointError(ValueError):
    """A checkpoint that is missing, foreign, of another kind, or does not fit its use."""


def save_checkpoint(path: str | Path, kind: str, payload: dict[str, Any]) -> None:
    """Atomically write ``payload`` tagged with the format and ``kind`` (e.g. ``world_model``)."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    atomic_torch_save({"format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind, **payload}, path)


def load_checkpoint(path: str | Path, kind: str) -> dict[str, Any]:
    """Read a checkpoint written by :func:`save_checkpoint` and check that it is a ``kind``."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        # weights_only: tensors and plain containers only, so a crafted pickle cannot run code
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a file that is not a checkpoint
        raise CheckpointError(f"{path} is not a readable checkpoint: {error}") from error
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a D2A checkpoint")
    if payload.get("format_version") != FORMAT_VERSION:
        version = payload.get("format_version")
        raise CheckpointError(f"{path} has checkpoint format v{version}, expected v{FORMAT_VERSION}: train it again")
    if payload.get("kind") != kind:
        raise CheckpointError(f"{path} is a {payload.get('kind')} checkpoint, not a {kind}")
    return payload


def load_for_resume(
    path: str | Path, kind: str, expected: dict[str, Any], keys: tuple[str, ...],
    upgrades: Mapping[str, Callable[[Any], Any]] | None = None,
) -> dict[str, Any] | None:
    """The checkpoint to resume from, or ``None`` when there is none yet.

    Refuses one whose ``keys`` differ from ``expected`` (another model, grid, task list...):
    resuming it would silently mix two runs. In a dict, a name the checkpoint lacks counts as
    off: a setting added after it was written, left at ``None`` or ``False``, does what older code did.
    ``upgrades`` reads an older entry as today's code would (e.g. a config parsed back through
    its dataclass, so that settings added since take their defaults) before it is compared.
    """
    if not Path(path).exists():
        return None
    previous = load_checkpoint(path, kind)
    for key in keys:
        old, new = previous.get(key), expected[key]
        if upgrades and key in upgrades and old is not None:
            try:
                old = upgrades[key](old)
            except (TypeError, ValueError, KeyError) as error:  # e.g. a setting this code does not know
                raise CheckpointError(f"{path} holds a {key} this code cannot read ({error}); "
                                      "choose another --out") from error
        if isinstance(old, dict) and isinstance(new, dict):
            old = {**{name: value if value is False else None for name, value in new.items()}, **old}
        if old != new:
            if isinstance(old, dict) and isinstance(new, dict):
                differences = ", ".join(f"{name}: {old.get(name)!r} -> {new.get(name)!r}"
                                        for name in sorted(set(old) | set(new)) if old.get(name) != new.get(name))
                raise CheckpointError(f"{path} was trained with another {key} ({differences}); "
                                      "choose another --out to start afresh")
            raise CheckpointError(f"{path} was trained with another {key} ({old}); choose another --out")
    return previous


def file_sha256(path: str | Path) -> str:
    """SHA-256 of a file's bytes: ties a checkpoint to the exact file it was trained with."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
