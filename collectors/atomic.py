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


def atomic_savez(path: str | Path, **arrays: Any) -> None:
    """``numpy.savez_compressed`` to ``path`` through a temporary file and an atomic rename."""
    import numpy as np

    _atomic_write(path, "wb", lambda handle: np.savez_compressed(handle, **arrays))


def atomic_torch_save(obj: Any, path: str | Path) -> None:
    """``torch.save`` to ``path`` through a temporary file and an atomic rename."""
    _atomic_write(path, "wb", lambda handle: torch.save(obj, handle))


LOCK_NAME = ".d2a-writer.lock"


class DirectoryBusyError(ValueError):
    """Another process holds the directory's writer lock."""

    @classmethod
    def of(cls, directory: str | Path) -> DirectoryBusyError:
        return cls(f"another process is writing to {directory}; wait for it to finish")


@contextmanager
def exclusive_writer(directory: str | Path, lock_name: str = LOCK_NAME) -> Iterator[Path]:
    """Hold ``directory``'s writer lock (creating the directory) for the ``with`` block.

    A second writer is refused at once rather than queued: two collections or two trainings
    into one place are a mistake to report, not a race to serialise. The lock is an ``flock``
    on ``lock_name``, so the system releases it when its process dies. A directory that
    cannot be written is refused here, before any work.
    """
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        handle = open(directory / lock_name, "a")
    except OSError as error:
        raise ValueError(f"cannot write to {directory}: {error.strerror or error}") from error
    with handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise DirectoryBusyError.of(directory) from None
        yield directory


def is_lock_file(path: Path) -> bool:
    """Whether ``path`` is a writer lock of :func:`exclusive_writer` (``.<name>.lock``)."""
    return path.name.startswith(".") and path.name.endswith(".lock")


def writer_active(directory: str | Path) -> bool:
    """Whether a live process holds one of ``directory``'s writer locks (a dead one's lock is free).

    Probing takes the lock for an instant and releases it; it never creates a lock file."""
    for entry in Path(directory).iterdir():
        if not is_lock_file(entry):
            continue
        with open(entry) as handle:
            try:
                fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return True
            fcntl.flock(handle, fcntl.LOCK_UN)
    return False


def holds_only_lock(directory: str | Path) -> bool:
    """Whether ``directory`` is empty but for writer locks (an untouched output directory)."""
    return all(is_lock_file(entry) for entry in Path(directory).iterdir())
