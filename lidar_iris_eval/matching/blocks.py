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


def _best_in_block(
    dist: np.ndarray, yaw: np.ndarray, rows: np.ndarray, exclude: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best column ``j <= i - exclude`` of each row; ties go to the smallest j."""
    cols = np.arange(dist.shape[1])
    allowed = cols[None, :] <= (rows[:, None] - exclude)
    masked = np.where(allowed & ~np.isnan(dist), dist, np.inf)
    match = np.argmin(masked, axis=1)
    best = masked[np.arange(len(rows)), match]
    best_yaw = yaw[np.arange(len(rows)), match]
    none = ~np.isfinite(best)
    match = np.where(none, -1, match)
    best_yaw = np.where(none, np.nan, best_yaw)
    return match.astype(np.int64), best, best_yaw


def _check_exclude(exclude: int) -> None:
    if exclude < 1:
        raise LirisError(option("exclude", exclude), "exclusion window must be at least 1 frame")


def best_matches(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    exclude: int,
    pair_budget: int = DEFAULT_PAIR_BUDGET,
    progress: Callable[[int], object] | None = None,
) -> BestMatches:
    """Exhaustive protocol 1 search: each query ``i >= exclude`` against ``j <= i - exclude``.

    A block of queries ``[a, b)`` is compared with the database ``[0, b - exclude)``
    (what its last query may see); the few pairs beyond each query's own
    limit are masked out, which wastes at most half a block per block.
    With a Dask engine active (``--scheduler``) the blocks are cluster tasks.
    """
    _check_exclude(exclude)
    from lidar_iris_eval import engine as engines

    if engines.current() is not None:
        from lidar_iris_eval.engine.tasks import best_matches_on_cluster

        return best_matches_on_cluster(engines.current(), descriptor, descriptors, exclude,
                                       pair_budget, progress)
    n = len(descriptors)
    queries = np.arange(min(exclude, n), n)
    match = np.empty(len(queries), dtype=np.int64)
    dist = np.empty(len(queries))
    yaw = np.empty(len(queries))
    evaluations = 0
    rows_per_block = block_rows(n, pair_budget)
    warm_up(descriptor, descriptors)  # compilation is not matching cost
    start = time.perf_counter()
    for a, b in query_blocks(min(exclude, n), n, rows_per_block):
        database = descriptors[: b - exclude]
        d, y = _pairwise(descriptor, descriptors[a:b], database)
        evaluations += d.size
        k = slice(a - queries[0], b - queries[0])
        match[k], dist[k], yaw[k] = _best_in_block(d, y, np.arange(a, b), exclude)
        if progress is not None:
            progress(b - a)
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
    if exclude is not None:
        _check_exclude(exclude)
    n = len(descriptors)
    symmetric = bool(descriptor.symmetric)
    matrix = np.empty((n, n), dtype=np.float32) if store else None
    first_query = min(exclude, n) if exclude is not None else n
    p1_match = np.empty(n - first_query, dtype=np.int64)
    p1_dist = np.empty(n - first_query)
    p1_yaw = np.empty(n - first_query)
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
        if exclude is not None and b > first_query:
            lo = max(a, first_query)
            rows = slice(lo - a, b - a)
            k = slice(lo - first_query, b - first_query)
            p1_match[k], p1_dist[k], p1_yaw[k] = _best_in_block(
                d[rows], y[rows], np.arange(lo, b), exclude
            )
        if progress is not None:
            progress(b - a)
    if matrix is not None:
        np.fill_diagonal(matrix, np.nan)
    seconds = time.perf_counter() - start - sink_s
    affinity = Affinity(matrix, seconds, evaluations, symmetric)
    if exclude is None:
        return affinity, None
    queries = np.arange(first_query, n)
    matches = BestMatches(queries, p1_match, p1_dist, p1_yaw, seconds, evaluations, "affinity")
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


def retrieval_matches(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    exclude: int,
    k: int,
    progress: Callable[[int], object] | None = None,
) -> BestMatches:
    """Protocol 1 through the descriptor's retrieval stage (see :mod:`.retrieval`)."""
    from lidar_iris_eval.matching.retrieval import two_stage_matches

    return two_stage_matches(descriptor, descriptors, exclude, k, progress)
