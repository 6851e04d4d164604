"""The block driver: descriptor distances for protocol 1 and 2 in bounded memory.

Descriptors provide ``pairwise(queries, database) -> (dist, yaw)`` for a block
of queries. This module decides which blocks to ask for, so that a 4541-frame
sequence never holds more than about ``pair_budget`` distances (plus yaws) in
float64 at once, and turns the blocks into

* the best match of every query over its database ``j <= i - E`` (protocol 1),
* the full ``(N, N)`` float32 affinity matrix (protocol 2),

or both from one pass, so a run with both protocols computes each distance
once. Protocol 1 best matches are always taken from the float64 block values,
so they are identical whichever path computed them. ``progress`` (optional)
is called with the number of query rows finished after each block, e.g. a
tqdm bar's ``update``.

Distances that come back NaN (e.g. LiDAR Iris when every bit is masked) are
treated as "no match": they never win a best-match search.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.errors import LirisError, option

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


def warm_up(descriptor: Descriptor, descriptors, candidates: int | None = None) -> None:
    """Run the matching kernels once on two descriptors, untimed.

    The first call of a numba kernel compiles it (or loads it from numba's
    cache); timing that would report compilation as matching cost (13x on a
    fresh install for LiDAR Iris protocol 2). Every timed loop calls this
    just before starting its clock.
    """
    if len(descriptors) < 2:
        return
    if candidates is None:  # the exhaustive loops: the batched kernel only
        _pairwise(descriptor, descriptors[:1], descriptors[:2])
        return
    descriptor.candidates(descriptors[:1], descriptors[:2], 1)  # the retrieval loop
    descriptor.distances(descriptors[0], descriptors[:2])


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


def protocol1_block(descriptor: Descriptor, descriptors, q: np.ndarray, lim: np.ndarray):
    """Best matches of queries ``q`` over ``j <= lim`` (one block; also a Dask task).

    The database is ``[0, max(lim) + 1)``, what the block's last query may
    see; returns ``(evaluations, match, distance, yaw)``.
    """
    database = descriptors[: int(lim.max()) + 1]
    d, y = _pairwise(descriptor, _rows(descriptors, q), database)
    return d.size, *_best_in_block(d, y, lim)


def best_matches(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    exclude,
    pair_budget: int = DEFAULT_PAIR_BUDGET,
    progress: Callable[[int], object] | None = None,
    executor=None,
) -> BestMatches:
    """Exhaustive protocol 1 search of each query over its database ``j <= limits[i]``.

    ``exclude`` is E (the standard ``j <= i - E``) or the ``(N,)`` per-query
    limits (:func:`query_limits`). A block of queries is compared with the
    database its last query may see; the few pairs beyond each query's own
    limit are masked out. ``executor`` (:mod:`lidar_iris_eval.executor`), when
    given, runs the blocks (e.g. as Dask tasks); the results do not change.
    """
    n = len(descriptors)
    limits = query_limits(n, exclude)
    queries = np.flatnonzero(limits >= 0)
    match = np.empty(len(queries), dtype=np.int64)
    dist = np.empty(len(queries))
    yaw = np.empty(len(queries))
    evaluations = 0
    blocks = query_row_blocks(limits, pair_budget)
    distributed = executor is not None and executor.distributes_blocks
    if not distributed:
        warm_up(descriptor, descriptors)  # compilation is not matching cost
    start = time.perf_counter()
    offsets = np.cumsum([0] + [len(q) for q in blocks])
    tasks = [(q, limits[q]) for q in blocks]
    if distributed:
        done = executor.imap(protocol1_block, tasks, shared=(descriptor, descriptors))
    else:
        done = ((i, protocol1_block(descriptor, descriptors, *t)) for i, t in enumerate(tasks))
    for index, (size, m, d, y) in done:
        k = slice(offsets[index], offsets[index + 1])
        match[k], dist[k], yaw[k] = m, d, y
        evaluations += int(size)
        if progress is not None:
            progress(len(blocks[index]))
    seconds = time.perf_counter() - start
    return BestMatches(queries, match, dist, yaw, seconds, evaluations, "exhaustive")


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

    ``exclude`` is E or the per-query limits (:func:`query_limits`).

    A symmetric descriptor is evaluated on the lower triangle only (each block
    of rows ``[a, b)`` against columns ``[0, b)``) and mirrored, so each
    unordered pair is computed once apart from the small diagonal blocks.
    Otherwise every row is computed against every column.

    ``sink(a, b, d)``, if given, receives every float64 block (rows ``[a, b)``,
    columns ``[0, width)``), e.g. the streaming PR counter of
    :mod:`~lidar_iris_eval.evaluation.streaming_pr`; its time is not counted as
    matching time. ``store=False`` keeps no matrix (``Affinity.matrix`` is None),
    so memory stays O(N) plus one block.
    """
    n = len(descriptors)
    limits = query_limits(n, exclude) if exclude is not None else None
    symmetric = bool(descriptor.symmetric)
    matrix = np.empty((n, n), dtype=np.float32) if store else None
    p1_match = np.full(n, -1, dtype=np.int64)
    p1_dist = np.full(n, np.inf)
    p1_yaw = np.full(n, np.nan)
    evaluations = 0
    sink_s = 0.0
    # a symmetric pass holds at most b columns per row; size blocks for the worst case
    rows_per_block = block_rows(n, pair_budget)
    warm_up(descriptor, descriptors)  # compilation is not matching cost
    start = time.perf_counter()
    for a, b in query_blocks(0, n, rows_per_block):
        width = b if symmetric else n
        d, y = _pairwise(descriptor, descriptors[a:b], descriptors[:width])
        evaluations += d.size
        if matrix is not None and symmetric:
            _fill_symmetric(matrix, d, a, b)
        elif matrix is not None:
            matrix[a:b] = d
        if sink is not None:
            sink_start = time.perf_counter()
            sink(a, b, d)
            sink_s += time.perf_counter() - sink_start
        if limits is not None:
            rows = np.flatnonzero(limits[a:b] >= 0)
            if len(rows):
                p1_match[a + rows], p1_dist[a + rows], p1_yaw[a + rows] = _best_in_block(
                    d[rows], y[rows], limits[a + rows])
        if progress is not None:
            progress(b - a)
    if matrix is not None:
        np.fill_diagonal(matrix, np.nan)
    seconds = time.perf_counter() - start - sink_s
    affinity = Affinity(matrix, seconds, evaluations, symmetric)
    if limits is None:
        return affinity, None
    queries = np.flatnonzero(limits >= 0)
    matches = BestMatches(queries, p1_match[queries], p1_dist[queries], p1_yaw[queries],
                          seconds, evaluations, "affinity")
    return affinity, matches


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


