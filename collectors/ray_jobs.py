"""Hand independent jobs (evaluation chunks, collection attempts, benchmark cells) to Ray.

Ray is optional (``pip install -e ".[ray]"``): nothing here imports it before a job asks for
it, and a missing install is a clear error, not a traceback from deep inside. A job is a
module-level function and its arguments; Ray runs it in a worker process on any node of the
cluster, with the CPUs (and GPUs) it asks for. Ray's workers set ``OMP_NUM_THREADS`` to the
job's CPU count, so torch uses as many threads as the job was given.

A worker that dies (killed, out of memory, its node lost) is retried by Ray up to
``max_retries`` times; a job still lost after that is reported as :class:`Lost`, never
silently dropped. An exception raised by the job itself (bad input, a bug) is not retried:
it reaches the caller as it is.

Example:
    >>> with ray_cluster("local"):  # doctest: +SKIP
    ...     for index, outcome in as_completed(pow, [(2, 3), (3, 2)]):
    ...         print(index, outcome)
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import Any

# ``--ray`` without an address: start a Ray instance on this machine for the duration of the command.
LOCAL = "local"
# Ray runs its workers at niceness 15, below every other process: on a machine with other work a
# local instance's jobs then hardly get a core (a two-cell bench took minutes to import torch
# beside five busy processes). The jobs are the command's work, so a local instance runs them at
# the command's own priority, as a run without Ray would.
LOCAL_SYSTEM_CONFIG = {"worker_niceness": 0}
INSTALL_HINT = 'Ray is not installed: pip install -e ".[ray]" (or pip install "ray>=2.40")'


def import_ray() -> ModuleType:
    """The ``ray`` module, or an ImportError that says how to install it."""
    try:
        import ray
    except ImportError as error:
        raise ImportError(INSTALL_HINT, name="ray") from error
    return ray


@contextlib.contextmanager
def ray_cluster(address: str = LOCAL, num_cpus: int | None = None) -> Iterator[ModuleType]:
    """Be connected to Ray for the duration of the block.

    ``address``: ``"local"`` starts a Ray instance on this machine (``num_cpus`` of its cores,
    default all; its workers at the caller's priority, :data:`LOCAL_SYSTEM_CONFIG`), ``"auto"``
    joins the cluster this machine belongs to, anything else is passed to ``ray.init`` (e.g.
    ``ray://head:10001``). If the caller is already connected (``ray.init``
    was called, e.g. with ``num_cpus=2``), that connection is used as it is and left open.
    """
    if not address:
        raise ValueError("a Ray address must be 'local', 'auto' or a cluster address")
    if num_cpus is not None and address != LOCAL:
        raise ValueError("num_cpus sizes a local Ray instance; a cluster has its own")
    ray = import_ray()
    if ray.is_initialized():
        yield ray
        return
    local = address == LOCAL
    ray.init(address=None if local else address, num_cpus=num_cpus, include_dashboard=False,
             log_to_driver=False, logging_level=logging.WARNING,  # the command's own lines, not Ray's chatter
             _system_config=LOCAL_SYSTEM_CONFIG if local else None)  # a cluster keeps its own settings
    try:
        yield ray
    finally:
        ray.shutdown()


def ray_connection(address: str | None) -> contextlib.AbstractContextManager:
    """:func:`ray_cluster` of ``address``, or a block that does nothing when it is ``None`` (a local run):
    commands open it once around all their Ray jobs."""
    return contextlib.nullcontext() if address is None else ray_cluster(address)


class JobsLost(RuntimeError):
    """Ray jobs whose workers died on every attempt: the command names what is missing."""


@dataclass(frozen=True)
class Lost:
    """A job whose worker died ``attempts`` times (killed, out of memory, node lost)."""

    reason: str
    attempts: int


def cluster_gpus(ray: ModuleType) -> int:
    """GPUs in the connected cluster (0 on a CPU-only one)."""
    return int(ray.cluster_resources().get("GPU", 0))


def _slots(ray: ModuleType, num_cpus: float) -> int:
    """How many jobs of ``num_cpus`` CPUs the connected cluster runs at once (at least 1)."""
    return max(1, int(ray.cluster_resources().get("CPU", 1) // max(num_cpus, 1e-9)))


def as_completed(
    function: Callable[..., Any],
    jobs: Iterable[tuple[Any, ...]],
    address: str = LOCAL,
    num_cpus: float = 1,
    num_gpus: float = 0,
    max_retries: int = 2,
    window: int | None = None,
) -> Iterator[tuple[int, Any]]:
    """Run ``function(*job)`` for every job on Ray; yield ``(index, outcome)`` as they finish.

    ``outcome`` is the function's return value, or :class:`Lost` when its worker died more
    than ``max_retries`` times. Jobs are submitted lazily, at most ``window`` at a time
    (default: twice as many as the cluster runs at once), so a caller that stops early
    (enough demonstrations) wastes little: closing the generator cancels the jobs in flight.
    """
    with ray_cluster(address) as ray:
        remote = ray.remote(function).options(
            num_cpus=num_cpus, num_gpus=num_gpus, max_retries=max_retries, retry_exceptions=False
        )
        window = window or 2 * _slots(ray, num_cpus)
        pending: dict[Any, int] = {}
        queue = enumerate(jobs)
        try:
            while True:
                for index, job in queue:
                    pending[remote.remote(*job)] = index
                    if len(pending) >= window:
                        break
                if not pending:
                    return
                (ready,), _ = ray.wait(list(pending), num_returns=1)
                index = pending.pop(ready)
                yield index, _outcome(ray, ready, max_retries)
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)


def _outcome(ray: ModuleType, ref: Any, max_retries: int) -> Any:
    """The job's result; a worker's death becomes :class:`Lost`, the job's own errors are raised."""
    exceptions = ray.exceptions
    try:
        return ray.get(ref)
    except exceptions.RayTaskError as error:  # raised by the job itself: the cause, not Ray's wrapper
        raise error.as_instanceof_cause() from None
    except (exceptions.WorkerCrashedError, exceptions.NodeDiedError, exceptions.OutOfMemoryError,
            exceptions.TaskCancelledError, exceptions.ObjectLostError) as error:
        return Lost(reason=f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}",
                    attempts=max_retries + 1)
