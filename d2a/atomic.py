"""Safe writes: atomic files (a killed writer never leaves a half-written file) and an
exclusive writer lock per directory (two writers never interleave)."""

from __future__ import annotations

import fcntl
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import torch


def _atomic_write(path: str | Path, mode: str, write: Callable[[IO[Any]], None]) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    with open(temporary, mode) as handle:
        write(handle)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(temporary, path)


def atomic_write_text(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file and an atomic rename."""
    _atomic_write(path, "w", lambda handle: handle.write(text))


def atomic_torch_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` to ``path`` through a temporary file and an atomic rename."""
    _atomic_write(path, "wb", lambda handle: torch.save(obj, handle))


LOCK_NAME = ".d2a-writer.lock"


class DirectoryBusyError(ValueError):
    """Another process holds the directory's writer lock."""


@contextmanager
def exclusive_writer(directory: str | Path) -> Iterator[Path]:
    """Hold ``directory``'s writer lock (creating the directory) for the ``with`` block.

    A second writer is refused at once rather than queued: two collections or two trainings
    into one directory are a mistake to report, not a race to serialise. The lock is an
    ``flock`` on :data:`LOCK_NAME`, so the system releases it when its process dies.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    with open(directory / LOCK_NAME, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DirectoryBusyError(f"another process is writing to {directory}; wait for it to finish") from None
        yield directory


def holds_only_lock(directory: str | Path) -> bool:
    """Whether ``directory`` is empty but for a writer lock (an untouched output directory)."""
    return all(entry.name == LOCK_NAME for entry in Path(directory).iterdir())
