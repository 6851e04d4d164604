"""Where the work runs, passed down as one object: serial, a process pool, or Dask.

The CLI builds one executor from ``--workers`` / ``--scheduler``
(:func:`open_executor`) and gives it to extraction
(:func:`~lidar_iris_eval.extract.extract`) and to the block passes
(:func:`~lidar_iris_eval.evaluation.evaluate.evaluate`); nothing below the
CLI reads global execution state.

* :class:`SerialExecutor` (``--workers 1``): everything in this process;
* :class:`ProcessExecutor` (``--scheduler processes``, the default): owns a
  local pool of ``workers`` processes behind ``imap`` (extraction chunks);
  matching blocks in this process (they share one large descriptor array);
* :class:`DaskExecutor` (``--scheduler local`` or ``tcp://HOST:PORT``):
  extraction chunks and matching blocks are cluster tasks. A matching task
  returns reductions only (per-row best matches, per-block counts), never a
  distance matrix, and the reductions merge exactly, so the metrics equal the
  serial ones bit for bit.

Every executor has ``imap(fn, tasks, shared=())``, which yields
``(index, fn(*shared, *tasks[index]))`` as tasks finish (any order), and
answers what its callers would otherwise decide by asking which kind it is:

* ``imap_progress(fn, tasks, shared, tick, sizes)``: ``imap`` that moves a
  progress bar unit by unit in this process, task by task elsewhere;
* ``run_blocks(fn, blocks, shared, warm_up, threaded)``: where a block pass
  runs (here after ``warm_up``, on ``concurrency()`` threads when the
  descriptor's blocks release the GIL, or as cluster tasks) and
  ``returns_blocks()``, whether a block task may return a whole block of
  distances;
* ``concurrency()``: how many tasks run at once (1: a caller may do the work
  itself and share its state, e.g. a scan cache);
* ``describe()`` and ``run_config()`` (``config.yaml``'s ``engine`` block).

A :class:`~lidar_iris_eval.errors.LirisError` raised in a task reaches the
caller as itself, from the pool and from Dask (it pickles with both parts),
so the CLI reports it as one line with exit code 2. Dask is an optional
extra: ``pip install "lidar-iris-eval[dask]"``.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from lidar_iris_eval.errors import LirisError

SCHEDULERS = ("processes", "local")
#: environment of worker processes: one numba / BLAS / OpenMP thread each
ONE_THREAD_ENV = {var: "1" for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                       "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}


@dataclass(frozen=True)
class SerialExecutor:
    """Everything in this process, in order."""

    workers: int = 1
    scheduler: str = "processes"

    def imap(self, fn: Callable, tasks: Sequence[tuple], shared: tuple = ()
             ) -> Iterator[tuple[int, Any]]:
        for index, task in enumerate(tasks):
            yield index, fn(*shared, *task)

    def imap_progress(self, fn: Callable, tasks: Sequence[tuple], shared: tuple = (),
                      tick: Callable[[int], object] | None = None,
                      sizes: Sequence[int] = ()) -> Iterator[tuple[int, Any]]:
        """:meth:`imap` that reports progress through ``tick(units done)``.

        Here ``fn`` gets ``tick`` itself (keyword ``tick``), so a bar moves
        unit by unit within a task (scan by scan in extraction) rather than
        chunk by chunk; a pool or cluster, whose tasks cannot call back into
        this process, calls ``tick(sizes[index])`` as each task finishes.
        """
        for index, task in enumerate(tasks):
            yield index, fn(*shared, *task, tick=tick)

    def concurrency(self) -> int:
        """How many tasks of :meth:`imap` run at once: 1 here.

        At 1 nothing is gained by shipping work out, so a caller may run it in
        this process itself and share its own state with it (registration
        shares one scan cache); above 1 the tasks run in other processes.
        """
        return 1

    def run_blocks(self, fn: Callable, tasks: Sequence[tuple], shared: tuple = (),
                   warm_up: Callable[[], object] | None = None, threaded: bool = False
                   ) -> Iterator[tuple[int, Any]]:
        """The tasks of a block pass, as :meth:`imap` yields them: here, in task order.

        Blocks share one large descriptor array, which a local pool would copy
        into every worker, so every local executor runs them in this process.
        ``threaded``: the tasks run on one thread each and release the GIL
        (a descriptor's ``threaded_blocks``), so :meth:`concurrency` of them
        run at once on threads of this process (one here: in order). Results
        still come in task order, so what a caller folds them into does not
        depend on the thread count. ``warm_up`` is called at once (not when
        the first block is asked for), so a caller that starts its clock after
        this call does not count the kernels' compilation as matching cost.
        """
        if warm_up is not None:
            warm_up()
        threads = self.concurrency() if threaded else 1
        if threads > 1 and len(tasks) > 1:
            return _thread_map(fn, tasks, shared, threads)
        return SerialExecutor.imap(self, fn, tasks, shared)

    def returns_blocks(self) -> bool:
        """Whether a block task may return a whole block of distances.

        True here: the blocks are computed in this process, so keeping them
        (an affinity matrix) ships nothing. A cluster's tasks return
        reductions only.
        """
        return True

    def describe(self) -> dict[str, Any]:
        return {"scheduler": self.scheduler, "workers": self.workers}

    def run_config(self) -> dict[str, Any]:
        """The ``engine`` block of a run's ``config.yaml``: the scheduler only.

        A local run's numbers do not depend on how many processes computed
        them, so its ``config.yaml`` does not change with ``--workers``; a
        cluster's block names its workers too (:meth:`DaskExecutor.run_config`).
        """
        return {"scheduler": self.scheduler}


def _thread_map(fn: Callable, tasks: Sequence[tuple], shared: tuple, threads: int
                ) -> Iterator[tuple[int, Any]]:
    """``(index, fn(*shared, *tasks[index]))`` in task order, ``threads`` tasks at a time.

    At most ``2 * threads`` tasks are submitted ahead of the one yielded
    next, so results waiting for an earlier task stay few (a block of
    distances is megabytes). A consumer that stops early (or an error)
    cancels the queued tasks and waits only for the running ones.
    """
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="liris-block")
    pending: deque = deque()
    try:
        for index, task in enumerate(tasks):
            pending.append((index, pool.submit(fn, *shared, *task)))
            if len(pending) >= 2 * threads:
                index_done, future = pending.popleft()
                yield index_done, future.result()
        while pending:
            index_done, future = pending.popleft()
            yield index_done, future.result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def stop_pool(pool) -> None:
    """Stop a ``ProcessPoolExecutor`` now: queued tasks cancelled, running ones killed.

    ``shutdown(wait=True)`` would wait for every running task (a compiled
    call holding its worker for seconds), so a Ctrl-C would not stop the run
    for that long; the workers ignore SIGINT (their parent reports it).
    """
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        with contextlib.suppress(Exception):
            process.terminate()
    for process in processes:
        with contextlib.suppress(Exception):
            process.join(timeout=1.0)


@dataclass(frozen=True)
class ProcessExecutor(SerialExecutor):
    """A local process pool of ``workers``: ``imap`` runs its tasks there (extraction
    chunks, registrations). Block passes stay in this process (:meth:`run_blocks`:
    they share one large descriptor array).

    ``shared`` is handed to each worker once (the pool's initializer), so a task
    ships only its own small arguments; a worker exits with the process that
    made the pool. Errors cross the process boundary as raised
    (:class:`~lidar_iris_eval.errors.LirisError` pickles with both its parts).
    An error or a Ctrl-C stops the pool at once (:func:`stop_pool`) instead of
    waiting for the tasks that are running.
    """

    workers: int = 2

    def imap(self, fn: Callable, tasks: Sequence[tuple], shared: tuple = ()
             ) -> Iterator[tuple[int, Any]]:
        if self.workers <= 1 or len(tasks) <= 1:
            yield from SerialExecutor.imap(self, fn, tasks, shared)
            return
        from concurrent.futures import ProcessPoolExecutor, as_completed

        pool = ProcessPoolExecutor(max_workers=min(self.workers, len(tasks)),
                                   initializer=_init_pool_worker,
                                   initargs=(fn, tuple(shared), os.getpid()))
        finished = False
        try:
            futures = {pool.submit(_pool_task, *task): index for index, task in enumerate(tasks)}
            for future in as_completed(futures):
                yield futures[future], future.result()
            finished = True
        finally:
            if finished:
                pool.shutdown(wait=True)
            else:  # an error, Ctrl-C or the consumer stopped: do not wait for running tasks
                stop_pool(pool)

    def concurrency(self) -> int:
        """``workers``: the pool's processes (1 or less: :meth:`imap` runs here)."""
        return max(1, self.workers)

    def imap_progress(self, fn: Callable, tasks: Sequence[tuple], shared: tuple = (),
                      tick: Callable[[int], object] | None = None,
                      sizes: Sequence[int] = ()) -> Iterator[tuple[int, Any]]:
        """:meth:`SerialExecutor.imap_progress`: in the pool, ticks as tasks finish;
        in this process (one worker or one task, as :meth:`imap`), unit by unit."""
        if self.workers <= 1 or len(tasks) <= 1:
            return SerialExecutor.imap_progress(self, fn, tasks, shared, tick, sizes)
        return _tick_when_done(self.imap(fn, tasks, shared), tick, sizes)


def _tick_when_done(results: Iterator[tuple[int, Any]], tick: Callable[[int], object] | None,
                    sizes: Sequence[int]) -> Iterator[tuple[int, Any]]:
    """``results`` of tasks run elsewhere, with ``tick(sizes[index])`` as each arrives."""
    for index, result in results:
        if tick is not None:
            tick(sizes[index])
        yield index, result


#: per-process state of pool workers: the task function and the shared arguments
_POOL: dict[str, Any] = {}


def _init_pool_worker(fn: Callable, shared: tuple, parent_pid: int) -> None:
    from lidar_iris_eval.lifetime import die_with_parent  # a SIGKILLed liris leaves no workers

    die_with_parent(parent_pid)
    _POOL["fn"], _POOL["shared"] = fn, shared


def _pool_task(*task):
    return _POOL["fn"](*_POOL["shared"], *task)


@dataclass
class DaskExecutor:
    """A Dask client: extraction chunks and matching blocks are its tasks.

    Attributes
    ----------
    client : the ``distributed.Client``.
    scheduler : ``local`` or the address given.
    workers : worker count when the executor started.
    """

    client: Any
    scheduler: str
    workers: int

    def imap(self, fn: Callable, tasks: Sequence[tuple], shared: tuple = ()
             ) -> Iterator[tuple[int, Any]]:
        """Submit every task (``shared`` scattered to every worker once); yield as done."""
        from distributed import as_completed

        client = self.client
        shared_f = client.scatter(list(shared), broadcast=True, hash=False) if shared else []
        futures = {client.submit(fn, *shared_f, *task, pure=False): index
                   for index, task in enumerate(tasks)}
        try:
            for future in as_completed(futures):
                result = future.result()
                index = futures[future]
                future.release()
                yield index, result
        finally:
            for future in futures:
                future.cancel()

    def concurrency(self) -> int:
        """The cluster's worker count when the executor started."""
        return max(1, self.workers)

    def imap_progress(self, fn: Callable, tasks: Sequence[tuple], shared: tuple = (),
                      tick: Callable[[int], object] | None = None,
                      sizes: Sequence[int] = ()) -> Iterator[tuple[int, Any]]:
        """:meth:`imap` with ``tick(sizes[index])`` as each task finishes."""
        return _tick_when_done(self.imap(fn, tasks, shared), tick, sizes)

    def run_blocks(self, fn: Callable, tasks: Sequence[tuple], shared: tuple = (),
                   warm_up: Callable[[], object] | None = None, threaded: bool = False
                   ) -> Iterator[tuple[int, Any]]:
        """The tasks of a block pass as cluster tasks (:meth:`imap`), in any order.

        ``warm_up`` is not called: nothing is matched in this process, and
        each worker compiles its kernels on its first block. ``threaded`` is
        not needed: the cluster's workers already run blocks side by side.
        """
        return self.imap(fn, tasks, shared)

    def returns_blocks(self) -> bool:
        """False: a block task returns reductions only, never a block of distances."""
        return False

    def describe(self) -> dict[str, Any]:
        """For config files: which scheduler, how many workers."""
        return {"scheduler": self.scheduler, "workers": self.workers}

    def run_config(self) -> dict[str, Any]:
        """The ``engine`` block of ``config.yaml``: the scheduler and its workers."""
        return self.describe()


Executor = SerialExecutor | ProcessExecutor | DaskExecutor


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


def local_executor(workers: int = 1) -> SerialExecutor:
    """Serial for one worker, a local process pool otherwise."""
    if workers < 1:
        raise LirisError(f"--workers {workers}", "must be at least 1")
    return SerialExecutor() if workers == 1 else ProcessExecutor(workers=workers)


def _put_back(saved: dict[str, str | None]) -> None:
    """Restore ``os.environ`` values saved as ``{name: value or None}``.

    distributed's nanny applies ``pre-spawn-environ`` to ``os.environ`` of the
    process that starts the cluster (this one) and leaves it there: during and
    after a ``--scheduler local`` run this process had ``NUMBA_NUM_THREADS=1``,
    numba's first parallel kernel here started one thread, and numba then
    refused every later compilation ("Cannot set NUMBA_NUM_THREADS to a
    different value once the threads have been launched") once the value
    changed back. The workers got their values when they were spawned.
    """
    for name, value in saved.items():
        if value is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = value


@contextlib.contextmanager
def open_executor(scheduler: str | None = "processes", workers: int = 1
                  ) -> Iterator[SerialExecutor | DaskExecutor]:
    """The executor of ``--scheduler`` / ``--workers`` for the duration of the block.

    ``local`` starts a LocalCluster of ``workers`` processes with one thread
    each (and one numba/BLAS thread, set before they start) and stops it
    afterwards; an address connects to that cluster and leaves it running.
    """
    if scheduler is None or scheduler == "processes":
        yield local_executor(workers)
        return
    check_scheduler(scheduler)
    distributed = _import_distributed()
    import dask

    with contextlib.ExitStack() as stack:
        if scheduler == "local":
            saved = {name: os.environ.get(name) for name in ONE_THREAD_ENV}
            stack.callback(_put_back, saved)  # again on leaving: a nanny may respawn a worker
            stack.enter_context(dask.config.set(
                {"distributed.nanny.pre-spawn-environ": dict(ONE_THREAD_ENV),
                 "distributed.worker.daemon": False}))
            cluster = stack.enter_context(distributed.LocalCluster(
                n_workers=max(1, workers), threads_per_worker=1, processes=True,
                dashboard_address=None, silence_logs=logging.ERROR))
            client = stack.enter_context(distributed.Client(cluster))
            _put_back(saved)
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
        yield DaskExecutor(client, scheduler, n_workers)
