"""The block driver: descriptor distances for protocol 1 and 2 in bounded memory.

Descriptors provide ``pairwise(queries, database) -> (dist, yaw)`` for a block
of queries. This module decides which blocks to ask for, so that a 4541-frame
sequence never holds more than about ``pair_budget`` distances (plus yaws) in
float64 at once, and turns the blocks into

* the best match of every query over its database ``j <= i - E`` (protocol 1),
* the full ``(N, N)`` float32 affinity matrix (protocol 2),

or both from one pass, so a run with both protocols computes each distance
once. Every pass is :func:`block_pass` with a list of reducers
(:class:`Reducer`: :class:`BestInRow`, :class:`StoreMatrix`, :class:`CallSink`
here; protocol 2's counters and stores in evaluation/streaming_pr.py), run in
this process or by an executor that distributes blocks. Protocol 1 best
matches are always taken from the float64 block values, so they are
identical whichever path computed them. ``progress`` (optional)
is called with the number of query rows finished after each block, e.g. a
tqdm bar's ``update``.

Distances that come back NaN (e.g. LiDAR Iris when every bit is masked) are
treated as "no match": they never win a best-match search.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.errors import LirisError, option
from lidar_iris_eval.executor import SerialExecutor

#: default number of distances computed per block (256 queries x 4096 frames)
DEFAULT_PAIR_BUDGET = 1 << 20
MIN_BLOCK_ROWS = 8


@dataclass(frozen=True)
class BestMatches:
    """The best database match of each query that has a database.

    Attributes
    ----------
    query : ``(Q,)`` query indices, ``i >= exclude``.
    match : ``(Q,)`` index of the best database frame, ``-1`` when every
        distance was undefined.
    distance : ``(Q,)`` float64 distance of that match (``inf`` when none).
    yaw_deg : ``(Q,)`` float64 yaw estimate of that match (``nan`` when none).
    seconds : wall time spent computing distances.
    n_evaluations : number of descriptor distances evaluated.
    source : how they were found: ``"exhaustive"``, ``"affinity"`` (taken from
        a protocol 2 pass), ``"candidates:K"`` (a global descriptor's retrieval
        stage) or ``"two-stage:K"`` (retrieval + verification).
    pose : ``(Q, 4, 4)`` estimated relative pose of each match (candidate's
        LiDAR frame -> query's), NaN where unknown; None when not estimated.
    inliers : ``(Q,)`` inlier counts of the verification, or None.
    """

    query: np.ndarray
    match: np.ndarray
    distance: np.ndarray
    yaw_deg: np.ndarray
    seconds: float
    n_evaluations: int
    source: str
    pose: np.ndarray | None = None
    inliers: np.ndarray | None = None


@dataclass(frozen=True)
class Affinity:
    """All-pairs distances: ``matrix[i, j] = distance(query i, candidate j)``.

    ``matrix`` is ``(N, N)`` float32 with a NaN diagonal. ``n_evaluations``
    counts the distances actually computed (about half of ``N(N-1)`` for a
    symmetric descriptor).
    """

    matrix: np.ndarray
    seconds: float
    n_evaluations: int
    symmetric: bool


def block_rows(n_database: int, pair_budget: int = DEFAULT_PAIR_BUDGET) -> int:
    """Queries per block so one block holds about ``pair_budget`` distances."""
    return max(MIN_BLOCK_ROWS, pair_budget // max(1, n_database))


def query_blocks(start: int, stop: int, rows: int) -> Iterator[tuple[int, int]]:
    """``(a, b)`` ranges covering ``[start, stop)`` in steps of ``rows``."""
    for a in range(start, stop, rows):
        yield a, min(a + rows, stop)


def warm_up(descriptor: Descriptor, descriptors) -> None:
    """Run the matching kernels once on two descriptors, untimed.

    The first call of a numba kernel compiles it (or loads it from numba's
    cache); timing that would report compilation as matching cost (13x on a
    fresh install for LiDAR Iris protocol 2). :func:`block_pass` has its
    executor call this just before starting its clock (a cluster's workers
    compile on their own).
    """
    if len(descriptors) < 2:
        return
    _pairwise(descriptor, descriptors[:1], descriptors[:2])


def _pairwise(descriptor: Descriptor, queries, database) -> tuple[np.ndarray, np.ndarray]:
    dist, yaw = descriptor.pairwise(queries, database)
    dist = np.asarray(dist, dtype=np.float64)
    yaw = np.asarray(yaw, dtype=np.float64)
    expected = (len(queries), len(database))
    if dist.shape != expected or yaw.shape != expected:
        raise RuntimeError(
            f"{descriptor.name}.pairwise returned shapes {dist.shape}, {yaw.shape}; "
            f"expected {expected}"
        )
    return dist, yaw


def frame_limits(n_frames: int, exclude: int) -> np.ndarray:
    """``(N,)`` limits of the standard rule: ``i - E``, ``-1`` for ``i < E``."""
    _check_exclude(exclude)
    limits = np.arange(n_frames, dtype=np.int64) - int(exclude)
    return np.where(limits >= 0, limits, -1).astype(np.int64)


def query_limits(n_frames: int, window) -> np.ndarray:
    """Per-query database limits from an exclusion window E (int) or a limits array.

    ``limits[i]`` is the last database frame query ``i`` may match; ``-1``
    means ``i`` is not a query. The standard rule ``j <= i - E`` is
    :func:`frame_limits`; peers' conventions give other arrays
    (:func:`~lidar_iris_eval.evaluation.ground_truth.database_limits`).
    """
    if isinstance(window, (int, np.integer)):
        return frame_limits(n_frames, int(window))
    limits = np.asarray(window, dtype=np.int64)
    if limits.shape != (n_frames,):
        raise LirisError("limits", f"{limits.shape} limits for {n_frames} frames")
    if np.any(limits >= np.arange(n_frames)):
        raise LirisError("limits", "a query may only match earlier frames")
    return np.where(limits >= 0, limits, -1)


def _best_in_block(
    dist: np.ndarray, yaw: np.ndarray, limits: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best column ``j <= limits[r]`` of each row ``r``; ties go to the smallest j."""
    cols = np.arange(dist.shape[1])
    allowed = cols[None, :] <= limits[:, None]
    masked = np.where(allowed & ~np.isnan(dist), dist, np.inf)
    match = np.argmin(masked, axis=1)
    best = masked[np.arange(len(limits)), match]
    best_yaw = yaw[np.arange(len(limits)), match]
    none = ~np.isfinite(best)
    match = np.where(none, -1, match)
    best_yaw = np.where(none, np.nan, best_yaw)
    return match.astype(np.int64), best, best_yaw


def _best_under_limits(
    dist: np.ndarray, yaw: np.ndarray, limits: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_best_in_block` for ``(K, R)`` limits at once: ``(K, R)`` match, distance, yaw.

    One prefix minimum per row serves every limit: the best column ``j <= L``
    is the prefix minimum at column ``L`` and, ties to the smallest ``j`` as
    in :func:`_best_in_block`, the last column where the prefix minimum
    strictly dropped. ``limits[k, r] = -1`` gives no match for that row.
    """
    rows, width = dist.shape
    masked = np.where(np.isnan(dist), np.inf, dist)
    prefix = np.minimum.accumulate(masked, axis=1) if width else masked
    dropped = np.empty((rows, width), dtype=bool)
    if width:
        dropped[:, 0] = True
        dropped[:, 1:] = masked[:, 1:] < prefix[:, :-1]
    where = np.maximum.accumulate(np.where(dropped, np.arange(width)[None, :], 0), axis=1) \
        if width else np.zeros((rows, 0), dtype=np.int64)
    lim = np.asarray(limits, dtype=np.int64)
    ok = lim >= 0
    col = np.clip(lim, 0, max(width - 1, 0))
    r = np.broadcast_to(np.arange(rows)[None, :], lim.shape)
    best = np.where(ok, prefix[r, col], np.inf) if width else np.full(lim.shape, np.inf)
    match = where[r, col] if width else np.zeros(lim.shape, dtype=np.int64)
    none = ~np.isfinite(best)
    best_yaw = np.where(none, np.nan, yaw[r, match] if width else np.nan)
    match = np.where(none, -1, match)
    return match.astype(np.int64), best, best_yaw


def best_in_block(dist: np.ndarray, yaw: np.ndarray, limits: np.ndarray):
    """Best matches of a block's rows under ``(R,)`` limits, or ``(K, R)`` limits (band)."""
    if np.ndim(limits) == 2:
        return _best_under_limits(dist, yaw, limits)
    return _best_in_block(dist, yaw, limits)


def stack_limits(n_frames: int, window) -> tuple[np.ndarray, bool]:
    """``(K, N)`` validated limits of ``window`` (E, one ``(N,)`` array or ``(K, N)``
    arrays) and whether several were given."""
    if not isinstance(window, (int, np.integer)) and np.ndim(window) == 2:
        return np.stack([query_limits(n_frames, w) for w in window]), True
    return query_limits(n_frames, window)[None, :], False


def split_matches(stacked: np.ndarray, queries: np.ndarray, match, dist, yaw, seconds,
                  evaluations, source) -> list[BestMatches]:
    """Per limit vector ``k``: the :class:`BestMatches` of its own queries
    (``stacked[k] >= 0``), from ``(K, Q)`` results over the union ``queries``."""
    out = []
    for k in range(len(stacked)):
        own = stacked[k][queries] >= 0
        out.append(BestMatches(queries[own], match[k][own], dist[k][own], yaw[k][own],
                               seconds, evaluations, source))
    return out


def _check_exclude(exclude: int) -> None:
    if exclude < 1:
        raise LirisError(option("exclude", exclude), "exclusion window must be at least 1 frame")


def _rows(descriptors, q: np.ndarray):
    """``descriptors[q]``, as a slice when ``q`` is a contiguous run (no copy)."""
    if len(q) and q[-1] - q[0] + 1 == len(q):
        return descriptors[int(q[0]) : int(q[-1]) + 1]
    return descriptors[q]


def query_row_blocks(limits: np.ndarray, pair_budget: int) -> list[np.ndarray]:
    """The protocol 1 blocks: runs of ``block_rows`` query indices (``limits >= 0``)."""
    queries = np.flatnonzero(limits >= 0)
    rows = block_rows(len(limits), pair_budget)
    return [queries[a : a + rows] for a in range(0, len(queries), rows)]


# --------------------------------------------------------------- the one block pass
class Reducer:
    """What a block pass does with each block of distances (see :func:`block_pass`).

    ``part(rows, d, y)`` runs where the block was computed (in this process,
    or in a Dask worker on a copy of the reducer as it was when the pass
    started) and returns a small picklable reduction of the float64 block
    ``d`` (rows ``rows`` of the queries x the first ``d.shape[1]`` database
    frames) and its yaws ``y``; ``merge(part)`` folds it into the reducer in
    this process. ``timed = False`` keeps a reducer's own time out of the
    matching time (the protocol 2 counters and stores).
    """

    timed: bool = True

    def part(self, rows: np.ndarray, d: np.ndarray, y: np.ndarray):  # pragma: no cover
        raise NotImplementedError

    def merge(self, part) -> None:  # pragma: no cover
        raise NotImplementedError


class BestInRow(Reducer):
    """Protocol 1: the best column ``j <= limits[i]`` of each query row (ties: smallest j).

    ``window`` is E, ``(N,)`` limits, or ``(K, N)`` limits (``--convention-band``):
    then every row is reduced under all ``K`` at once (one prefix minimum) and
    :meth:`result` gives ``K`` :class:`BestMatches`.
    """

    def __init__(self, n: int, window):
        self.stacked, self.several = stack_limits(n, window)
        self.union = self.stacked.max(axis=0)
        shape = (len(self.stacked), n)
        self.match = np.full(shape, -1, dtype=np.int64)
        self.dist = np.full(shape, np.inf)
        self.yaw = np.full(shape, np.nan)

    def part(self, rows, d, y):
        sel = np.flatnonzero(self.union[rows] >= 0)
        if len(sel) == 0:
            return None
        if len(sel) < len(rows):
            rows, d, y = rows[sel], d[sel], y[sel]
        if self.several:
            return rows, *_best_under_limits(d, y, self.stacked[:, rows])
        return rows, *_best_in_block(d, y, self.stacked[0, rows])

    def merge(self, part) -> None:
        if part is not None:
            rows, match, dist, yaw = part
            self.match[:, rows], self.dist[:, rows], self.yaw[:, rows] = match, dist, yaw

    def blocks(self, pair_budget: int) -> list[tuple[np.ndarray, int]]:
        """Protocol 1's own blocks: runs of queries against what their last one may see."""
        return [(q, int(self.union[q].max()) + 1)
                for q in query_row_blocks(self.union, pair_budget)]

    def result(self, seconds: float, evaluations: int, source: str):
        """The :class:`BestMatches` (a list of ``K`` under ``(K, N)`` limits)."""
        queries = np.flatnonzero(self.union >= 0)
        out = split_matches(self.stacked, queries, self.match[:, queries],
                            self.dist[:, queries], self.yaw[:, queries], seconds,
                            evaluations, source)
        return out if self.several else out[0]


class StoreMatrix(Reducer):
    """The ``(N, N)`` float32 affinity; a symmetric descriptor's lower triangle, mirrored.

    Local passes only (``part`` returns the whole block).
    """

    def __init__(self, n: int, symmetric: bool):
        self.matrix = np.empty((n, n), dtype=np.float32)
        self.symmetric = symmetric

    def part(self, rows, d, y):
        return int(rows[0]), int(rows[-1]) + 1, d

    def merge(self, part) -> None:
        a, b, d = part
        if self.symmetric:
            _fill_symmetric(self.matrix, d, a, b)
        else:
            self.matrix[a:b] = d

    def finish(self) -> np.ndarray:
        np.fill_diagonal(self.matrix, np.nan)
        return self.matrix


class CallSink(Reducer):
    """``sink(a, b, d)`` on every block (rows ``[a, b)``), in this process; untimed."""

    timed = False

    def __init__(self, sink: Callable[[int, int, np.ndarray], object]):
        self.sink = sink

    def part(self, rows, d, y):
        return int(rows[0]), int(rows[-1]) + 1, d

    def merge(self, part) -> None:
        self.sink(*part)


def _block_task(descriptor, queries, database, reducers, rows, width):
    """One block: its distances once, then every reducer's part (also a Dask task).

    Returns ``(distances computed, parts, seconds of the untimed reducers' parts,
    process id)``: the pass subtracts those seconds from its wall clock only
    when the block ran in its own process (elsewhere they overlapped it).
    """
    database = queries if database is None else database
    d, y = _pairwise(descriptor, _rows(queries, rows), database[:width])
    parts, untimed = [], 0.0
    for reducer in reducers:
        if reducer.timed:
            parts.append(reducer.part(rows, d, y))
        else:
            began = time.perf_counter()
            parts.append(reducer.part(rows, d, y))
            untimed += time.perf_counter() - began
    return d.size, parts, untimed, os.getpid()


#: the executor of a pass given none: everything in this process
_HERE = SerialExecutor()


def block_pass(descriptor: Descriptor, descriptors, blocks, reducers, executor=None,
               progress: Callable[[int], object] | None = None, database=None
               ) -> tuple[int, float]:
    """The one block loop: each block's distances computed once, handed to every reducer.

    ``blocks`` are ``(rows, width)``: query indices (a contiguous run is read
    as a slice) against database frames ``[0, width)``. ``database`` is the
    descriptors queries are matched against (another session's); default the
    queries' own. ``executor`` (:mod:`lidar_iris_eval.executor`; default this
    process) decides where the blocks run (``run_blocks``): a local one in this
    process, after warming the kernels up (on several threads when the
    descriptor's ``threaded_blocks`` says its blocks release the GIL; merged
    in block order all the same); Dask as tasks returning the reducers'
    parts only. Merges are exact and in block order here, so the results do not
    depend on the executor. Returns ``(evaluations, seconds)``: distances computed
    and matching wall time (without the untimed reducers' time spent in this
    process).
    """
    reducers = list(reducers)
    runner = _HERE if executor is None else executor
    shared = (descriptor, descriptors, database, tuple(reducers))
    results = runner.run_blocks(_block_task, blocks, shared,
                                warm_up=lambda: warm_up(descriptor, descriptors),
                                threaded=bool(getattr(descriptor, "threaded_blocks", False)))
    here = os.getpid()
    evaluations, untimed = 0, 0.0
    start = time.perf_counter()
    for index, (size, parts, parts_s, pid) in results:
        if pid == here:
            untimed += parts_s
        for reducer, part in zip(reducers, parts, strict=True):
            if reducer.timed:
                reducer.merge(part)
            else:
                began = time.perf_counter()
                reducer.merge(part)
                untimed += time.perf_counter() - began
        evaluations += int(size)
        if progress is not None:
            progress(len(blocks[index][0]))
    return evaluations, time.perf_counter() - start - untimed


def row_blocks(n: int, pair_budget: int, symmetric: bool) -> list[tuple[np.ndarray, int]]:
    """The all-pairs blocks: rows ``[a, b)`` against ``[0, b)`` (symmetric) or ``[0, n)``."""
    return [(np.arange(a, b), b if symmetric else n)
            for a, b in query_blocks(0, n, block_rows(n, pair_budget))]


def best_matches(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    exclude,
    pair_budget: int = DEFAULT_PAIR_BUDGET,
    progress: Callable[[int], object] | None = None,
    executor=None,
):
    """Exhaustive protocol 1 search of each query over its database ``j <= limits[i]``.

    ``exclude`` is E (the standard ``j <= i - E``) or the ``(N,)`` per-query
    limits (:func:`query_limits`). A block of queries is compared with the
    database its last query may see; the few pairs beyond each query's own
    limit are masked out. ``executor`` (:mod:`lidar_iris_eval.executor`), when
    given, decides where the blocks run (see :func:`block_pass`; e.g. as Dask
    tasks); the results do not change.

    ``exclude`` may also be ``(K, N)`` limits (``--convention-band``): one pass
    over the union of their queries and databases, and a list of ``K``
    :class:`BestMatches`, each equal to a search under its own limits.
    """
    best = BestInRow(len(descriptors), exclude)
    evaluations, seconds = block_pass(descriptor, descriptors, best.blocks(pair_budget), [best],
                                      executor, progress)
    return best.result(seconds, evaluations, "exhaustive")


def affinity_matrix(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    exclude: int | None = None,
    pair_budget: int = DEFAULT_PAIR_BUDGET,
    progress: Callable[[int], object] | None = None,
    sink: Callable[[int, int, np.ndarray], object] | None = None,
    store: bool = True,
) -> tuple[Affinity, BestMatches | None]:
    """The ``(N, N)`` float32 affinity and, when ``exclude`` is given, protocol 1 matches.

    ``exclude`` is E or the per-query limits (:func:`query_limits`), or ``(K, N)``
    limits: then a list of ``K`` :class:`BestMatches` (see :func:`best_matches`).

    A symmetric descriptor is evaluated on the lower triangle only (each block
    of rows ``[a, b)`` against columns ``[0, b)``) and mirrored, so each
    unordered pair is computed once apart from the small diagonal blocks.
    Otherwise every row is computed against every column.

    ``sink(a, b, d)``, if given, receives every float64 block (rows ``[a, b)``,
    columns ``[0, width)``); its time is not counted as matching time.
    ``store=False`` keeps no matrix (``Affinity.matrix`` is None), so memory
    stays O(N) plus one block. One :func:`block_pass` with the reducers asked for.
    """
    n = len(descriptors)
    symmetric = bool(descriptor.symmetric)
    matrix = StoreMatrix(n, symmetric) if store else None
    best = BestInRow(n, exclude) if exclude is not None else None
    reducers = [r for r in (matrix, CallSink(sink) if sink is not None else None, best)
                if r is not None]
    evaluations, seconds = block_pass(descriptor, descriptors,
                                      row_blocks(n, pair_budget, symmetric), reducers,
                                      progress=progress)
    affinity = Affinity(matrix.finish() if matrix is not None else None, seconds, evaluations,
                        symmetric)
    if best is None:
        return affinity, None
    return affinity, best.result(seconds, evaluations, "affinity")


def _fill_symmetric(matrix: np.ndarray, d: np.ndarray, a: int, b: int) -> None:
    """Write rows ``[a, b)`` x columns ``[0, b)`` and their mirror image.

    Inside the diagonal block only the strict lower triangle is trusted, so the
    matrix is exactly symmetric even if a kernel rounds ``d(i, j)`` and
    ``d(j, i)`` differently.
    """
    block = d.astype(np.float32)
    matrix[a:b, :a] = block[:, :a]
    matrix[:a, a:b] = block[:, :a].T
    lower = np.tril(block[:, a:b], -1)
    matrix[a:b, a:b] = lower + lower.T


