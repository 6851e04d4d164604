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


def protocol1_block(descriptor: Descriptor, descriptors, q: np.ndarray, lim: np.ndarray):
    """Best matches of queries ``q`` over ``j <= lim`` (one block; also a Dask task).

    The database is ``[0, max(lim) + 1)``, what the block's last query may
    see; returns ``(evaluations, match, distance, yaw)``.
    """
    database = descriptors[: int(lim.max()) + 1]
    d, y = _pairwise(descriptor, _rows(descriptors, q), database)
    return d.size, *best_in_block(d, y, lim)


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
    given, runs the blocks (e.g. as Dask tasks); the results do not change.

    ``exclude`` may also be ``(K, N)`` limits (``--convention-band``): one pass
    over the union of their queries and databases, and a list of ``K``
    :class:`BestMatches`, each equal to a search under its own limits.
    """
    n = len(descriptors)
    stacked, several = stack_limits(n, exclude)
    union = stacked.max(axis=0)
    queries = np.flatnonzero(union >= 0)
    k_lim = len(stacked)
    match = np.empty((k_lim, len(queries)), dtype=np.int64)
    dist = np.empty((k_lim, len(queries)))
    yaw = np.empty((k_lim, len(queries)))
    evaluations = 0
    blocks = query_row_blocks(union, pair_budget)
    distributed = executor is not None and executor.distributes_blocks
    if not distributed:
        warm_up(descriptor, descriptors)  # compilation is not matching cost
    start = time.perf_counter()
    offsets = np.cumsum([0] + [len(q) for q in blocks])
    tasks = [(q, stacked[:, q] if several else stacked[0, q]) for q in blocks]
    if distributed:
        done = executor.imap(protocol1_block, tasks, shared=(descriptor, descriptors))
    else:
        done = ((i, protocol1_block(descriptor, descriptors, *t)) for i, t in enumerate(tasks))
    for index, (size, m, d, y) in done:
        k = slice(offsets[index], offsets[index + 1])
        match[:, k], dist[:, k], yaw[:, k] = m, d, y
        evaluations += int(size)
        if progress is not None:
            progress(len(blocks[index]))
    seconds = time.perf_counter() - start
    out = split_matches(stacked, queries, match, dist, yaw, seconds, evaluations, "exhaustive")
    return out if several else out[0]


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
    columns ``[0, width)``), e.g. the streaming PR counter of
    :mod:`~lidar_iris_eval.evaluation.streaming_pr`; its time is not counted as
    matching time. ``store=False`` keeps no matrix (``Affinity.matrix`` is None),
    so memory stays O(N) plus one block.
    """
    n = len(descriptors)
    stacked, several = stack_limits(n, exclude) if exclude is not None else (None, False)
    limits = stacked.max(axis=0) if stacked is not None else None
    symmetric = bool(descriptor.symmetric)
    matrix = np.empty((n, n), dtype=np.float32) if store else None
    k_lim = 0 if stacked is None else len(stacked)
    p1_match = np.full((k_lim, n), -1, dtype=np.int64)
    p1_dist = np.full((k_lim, n), np.inf)
    p1_yaw = np.full((k_lim, n), np.nan)
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
                p1_match[:, a + rows], p1_dist[:, a + rows], p1_yaw[:, a + rows] = \
                    _best_under_limits(d[rows], y[rows], stacked[:, a + rows]) if several \
                    else _best_in_block(d[rows], y[rows], stacked[0, a + rows])
        if progress is not None:
            progress(b - a)
    if matrix is not None:
        np.fill_diagonal(matrix, np.nan)
    seconds = time.perf_counter() - start - sink_s
    affinity = Affinity(matrix, seconds, evaluations, symmetric)
    if limits is None:
        return affinity, None
    queries = np.flatnonzero(limits >= 0)
    matches = split_matches(stacked, queries, p1_match[:, queries], p1_dist[:, queries],
                            p1_yaw[:, queries], seconds, evaluations, "affinity")
    return affinity, matches if several else matches[0]


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


