"""Where the work runs: today's local process pool, or a Dask cluster.

``--scheduler`` picks one of

* ``processes`` (default): extraction chunks in a local process pool
  (``--workers``), matching in this process; nothing here is used;
* ``local``: an embedded ``dask.distributed`` LocalCluster of ``--workers``
  worker processes, one thread each;
* ``tcp://HOST:PORT`` (any Dask scheduler address): an existing cluster.

With Dask, extraction chunks and matching blocks are tasks. A matching task
returns reductions only: the per-row best matches of protocol 1 and the
per-block negative counts of protocol 2
(:class:`~lidar_iris_eval.evaluation.streaming_pr.StreamingPR`), never a
distance matrix, so the client's memory stays O(N + positives). Every
reduction is exact (integer sums, minima, maxima; the same block boundaries
as the local pass), so the metrics equal the default scheduler's exactly.

The library code asks :func:`current` whether an engine is active; the CLI
activates one for the duration of a run with :func:`use_scheduler`.
Dask is an optional extra: ``pip install "lidar-iris-eval[dask]"``.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from lidar_iris_eval.errors import LirisError

SCHEDULERS = ("processes", "local")
#: environment of worker processes: one numba / BLAS / OpenMP thread each
ONE_THREAD_ENV = {var: "1" for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                       "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}

_CURRENT: list[DaskEngine] = []


@dataclass
class DaskEngine:
    """An active Dask client and what it runs on.

    Attributes
    ----------
    client : the ``distributed.Client``.
    scheduler : ``local`` or the address given.
    workers : worker count when the engine started.
    """

    client: Any
    scheduler: str
    workers: int

    def describe(self) -> dict[str, Any]:
        """For config files: which scheduler, how many workers."""
        return {"scheduler": self.scheduler, "workers": self.workers}


def current() -> DaskEngine | None:
    """The Dask engine of the running evaluation, or None (local processes)."""
    return _CURRENT[-1] if _CURRENT else None


def check_scheduler(value: str) -> str:
    """``processes``, ``local`` or a scheduler address; anything else is an error."""
    if value in SCHEDULERS or "://" in value:
        return value
    raise LirisError(f"--scheduler {value}",
                     "choose processes, local or a Dask scheduler address (tcp://HOST:PORT)")


def _import_distributed():
    try:
        import distributed
    except ImportError:
        raise LirisError("--scheduler", "Dask is not installed; install the optional extra: "
                         "pip install 'lidar-iris-eval[dask]'") from None
    return distributed


def _one_thread_per_worker() -> None:
    """Run on every worker: numba (and BLAS, where threadpoolctl exists) on one thread."""
    for var, value in ONE_THREAD_ENV.items():
        os.environ.setdefault(var, value)
    try:
        import numba

        numba.set_num_threads(1)
    except (ImportError, ValueError):
        pass
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass


@contextlib.contextmanager
def use_scheduler(scheduler: str | None, workers: int = 1) -> Iterator[DaskEngine | None]:
    """Activate ``scheduler`` for the block: None/``processes`` activate nothing.

    ``local`` starts a LocalCluster of ``workers`` processes with one thread
    each (and one numba/BLAS thread, set before they start) and stops it
    afterwards; an address connects to that cluster and leaves it running.
    """
    if scheduler is None or scheduler == "processes":
        yield None
        return
    check_scheduler(scheduler)
    distributed = _import_distributed()
    import dask

    cluster = None
    with contextlib.ExitStack() as stack:
        if scheduler == "local":
            stack.enter_context(dask.config.set(
                {"distributed.nanny.pre-spawn-environ": dict(ONE_THREAD_ENV),
                 "distributed.worker.daemon": False}))
            cluster = stack.enter_context(distributed.LocalCluster(
                n_workers=max(1, workers), threads_per_worker=1, processes=True,
                dashboard_address=None, silence_logs=logging.ERROR))
            client = stack.enter_context(distributed.Client(cluster))
        else:
            try:
                client = stack.enter_context(distributed.Client(scheduler, timeout="20s"))
            except OSError as err:
                raise LirisError(f"--scheduler {scheduler}",
                                 f"cannot reach the Dask scheduler: {err}") from None
        client.run(_one_thread_per_worker)
        n_workers = len(client.scheduler_info().get("workers", {}))
        if n_workers == 0:
            client.wait_for_workers(1, timeout=60)
            n_workers = len(client.scheduler_info().get("workers", {}))
        engine = DaskEngine(client, scheduler, n_workers)
        _CURRENT.append(engine)
        try:
            yield engine
        finally:
            _CURRENT.remove(engine)
