"""Chunk passes as Dask tasks: the executor of a partitioned dataset on a Dask cluster.

Each task is one shard: the worker reads it (:meth:`symcal.data.shards.Shard.read`), evaluates
the pass chunk by chunk and returns a small reduction (a number, ``Jᵀg`` and ``JᵀJ``, or
an R factor), so a worker holds one shard at a time and the lead never holds the log.
The lead reduces the shards' results in shard order (:func:`symcal.solvers.passes.run_pass`).

This module alone imports Dask (``distributed``), when an executor is made.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any, TypeVar

from symcal.base.errors import SymcalError, excerpt
from symcal.solvers.executor import usable_cores

if TYPE_CHECKING:
    from distributed import Client

T = TypeVar("T")

#: Environment of the embedded cluster's workers: one BLAS thread each.
WORKER_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


class DaskExecutor:
    """Tasks on a Dask cluster through ``client``; results in the order of the pieces.

    Parameters
    ----------
    client
        A ``distributed.Client``.
    """

    remote = True

    def __init__(self, client: Client) -> None:
        self.client = client

    def map(self, task: Callable[[Any], T], pieces: Iterable[Any]) -> Iterator[T]:
        """``task(piece)`` for every piece on the cluster, gathered in order."""
        items = list(pieces)
        if not items:
            return iter(())
        futures = self.client.map(task, items, pure=False)
        return self._gather(futures)

    @staticmethod
    def _gather(futures: list[Any]) -> Iterator[T]:
        try:
            for future in futures:
                yield future.result()
        finally:
            for future in futures:
                future.cancel()

    def __repr__(self) -> str:
        return f"DaskExecutor({self.client!r})"


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None,
                option: str | None = None) -> Iterator[Client]:
    """A ``distributed.Client`` to the scheduler at ``scheduler``, or to an embedded local
    cluster of ``workers`` processes (default: one per usable core, one thread and one
    BLAS thread each), closed when the block ends.

    Parameters
    ----------
    scheduler
        Address of a running Dask scheduler (``tcp://host:8786``), or None.
    workers
        Worker processes of the local cluster.
    option
        The command-line option that named the scheduler, for the error message.

    Raises
    ------
    SymcalError
        When the scheduler cannot be reached (exit code 2).
    """
    from distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as exc:
            named = f"{option} {excerpt(scheduler, 80)}: " if option else ""
            raise SymcalError(f"{named}cannot reach the Dask scheduler "
                              f"{excerpt(scheduler, 80)} ({excerpt(exc, 120)})") from None
        try:
            yield client
        finally:
            client.close()
        return
    with LocalCluster(n_workers=workers or usable_cores(), threads_per_worker=1,
                      processes=True, dashboard_address=None, silence_logs=logging.ERROR,
                      env=dict(WORKER_ENV)) as cluster, Client(cluster) as client:
        yield client


@contextlib.contextmanager
def dask_executor(scheduler: str | None = None,
                  workers: int | None = None) -> Iterator[DaskExecutor]:
    """A :class:`DaskExecutor` on :func:`dask_client` (the same arguments).

    Raises
    ------
    SymcalError
        When the scheduler cannot be reached (exit code 2).
    """
    with dask_client(scheduler, workers) as client:
        yield DaskExecutor(client)
