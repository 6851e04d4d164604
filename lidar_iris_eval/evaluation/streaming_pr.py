"""Protocol 2's exact PR curve in O(N + positives) memory, block by block.

Protocol 2 scores every ordered pair: 20.6 M of them at KITTI 00 length,
400 M at 20k frames. Holding them (an ``N x N`` affinity, a positive mask,
sorted copies) grows with N². But the curve only *changes* at positive
distances: between two consecutive distinct positive distances ``P[k-1] <
P[k]`` only false positives are accepted. So it suffices to know, per gap
``(P[k-1], P[k]]``, how many negatives fall in it, how many of those tie
with ``P[k]``, and the largest one strictly below ``P[k]``; plus the
smallest negative (the curve's first point) and the largest (its last).
Those are a few arrays of ``len(P) + 1`` entries, accumulated one block of
distances at a time with ``searchsorted``.

:meth:`StreamingPR.curve` returns *exactly* the points that
:func:`~lidar_iris_eval.evaluation.metrics.reduce_curve` keeps from
:func:`~lidar_iris_eval.evaluation.metrics.pr_curve` over all predictions
(the same thresholds, integer counts and float divisions; tested on random
data with ties), hence the same AP, max F1, R@100P and EP and the same
``pr.csv``. Metrics are exact, not binned.

The positive distances must be known before the negatives are bucketed.
:func:`positive_values` computes them first (a few calls of the
descriptor's ``pairwise`` on the positive pairs only); the block pass then
checks every positive it meets against them, so a descriptor whose batched
numbers depended on the batch shape would be caught (and the pass redone)
rather than silently mis-scored.

The one difference from ``reduce_curve``: with *no* positive at all, recall
is undefined (NaN) everywhere and ``reduce_curve`` keeps every point; here
the curve holds only the first and last point. Every summary number is
undefined in that case anyway.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.evaluation.metrics import PRCurve
from lidar_iris_eval.matching.blocks import Affinity

#: queries per pairwise call when computing the positive distances first (KITTI-00 scale,
#: LiDAR Iris: 64 queries a call evaluated 383k distances in 4.5 s, 8 evaluated 73k in 1.4 s)
POSITIVE_QUERY_CHUNK = 8


class StreamingPR:
    """Accumulates negatives against known positive distances; gives the exact reduced curve.

    Parameters
    ----------
    positives : ``(K,)`` distances of every positive prediction (non-finite
        ones are never accepted and are dropped, as :func:`pr_curve` does).
    weight : multiplicity of every prediction (2 when each unordered pair
        stands for two ordered ones).
    """

    def __init__(self, positives: np.ndarray, weight: int = 1):
        pos = np.asarray(positives, dtype=np.float64).ravel()
        pos = np.sort(pos[np.isfinite(pos)])
        self.weight = int(weight)
        self.levels = np.unique(pos)  # P: distinct positive distances
        #: positives <= P[k]
        self.pos_at_most = np.searchsorted(pos, self.levels, side="right").astype(np.int64)
        self.n_pos = len(pos)
        m = len(self.levels)
        #: negatives in (P[k-1], P[k]] (bucket m: above P[-1])
        self.bucket = np.zeros(m + 1, dtype=np.int64)
        #: negatives equal to P[k]
        self.tied = np.zeros(m, dtype=np.int64)
        #: largest negative strictly inside (P[k-1], P[k]) (bucket m: the largest above P[-1])
        self.gap_max = np.full(m + 1, -np.inf)
        self.neg_min = np.inf
        self.neg_min_count = 0

    @property
    def n_negatives(self) -> int:
        """Finite negatives accumulated so far (unweighted)."""
        return int(self.bucket.sum())

    def add_negatives(self, distances: np.ndarray) -> None:
        """Accumulate a block of negative predictions (any shape; non-finite ignored).

        The block is sorted (a vectorised sort of a few MB) and the gap edges are
        found by searching the *levels* in it, which is several times faster than
        searching a million unsorted values among the levels.
        """
        d = np.asarray(distances).ravel()
        d = np.sort(d[np.isfinite(d)]).astype(np.float64)
        if d.size == 0:
            return
        levels = self.levels
        m = len(levels)
        left = np.searchsorted(d, levels, side="left")  # first value >= P[k]
        right = np.searchsorted(d, levels, side="right")  # first value > P[k]
        edges = np.concatenate([[0], right, [d.size]])
        self.bucket += np.diff(edges)  # (P[k-1], P[k]] and the tail
        self.tied += right - left
        # the largest value strictly below P[k] inside its gap: d[left[k] - 1] if in the gap
        below = left - 1
        inside = below >= edges[:m]
        if inside.any():
            k = np.flatnonzero(inside)
            np.maximum.at(self.gap_max, k, d[below[k]])
        if edges[m] < d.size:  # values above every positive: the largest is the last point
            self.gap_max[m] = max(self.gap_max[m], float(d[-1]))
        low = float(d[0])
        count = int(np.searchsorted(d, low, side="right"))
        if low < self.neg_min:
            self.neg_min, self.neg_min_count = low, count
        elif low == self.neg_min:
            self.neg_min_count += count

    def fresh(self) -> StreamingPR:
        """An empty accumulator for the same positives (no re-sorting), e.g. per task."""
        out = object.__new__(StreamingPR)
        out.weight, out.levels, out.pos_at_most, out.n_pos = (
            self.weight, self.levels, self.pos_at_most, self.n_pos)
        out.bucket = np.zeros_like(self.bucket)
        out.tied = np.zeros_like(self.tied)
        out.gap_max = np.full_like(self.gap_max, -np.inf)
        out.neg_min, out.neg_min_count = np.inf, 0
        return out

    def merge(self, other: StreamingPR) -> None:
        """Add another accumulator's negatives (same positives), e.g. from another worker."""
        if not np.array_equal(self.levels, other.levels) or self.weight != other.weight:
            raise ValueError("accumulators of different positives cannot be merged")
        self.bucket += other.bucket
        self.tied += other.tied
        np.maximum(self.gap_max, other.gap_max, out=self.gap_max)
        if other.neg_min < self.neg_min:
            self.neg_min, self.neg_min_count = other.neg_min, other.neg_min_count
        elif other.neg_min == self.neg_min:
            self.neg_min_count += other.neg_min_count

    def curve(self, denominator: int) -> PRCurve:
        """The exact PR curve reduced as :func:`reduce_curve` reduces it."""
        m = len(self.levels)
        neg_cum = np.cumsum(self.bucket)  # negatives <= P[k] (k < m); total at m
        prev_pos = np.concatenate([[0], self.pos_at_most]).astype(np.int64)[:m]
        prev_neg = np.concatenate([[0], neg_cum]).astype(np.int64)[:m]
        has_gap = self.gap_max[:m] > -np.inf  # a point just before P[k]
        parts_t = [self.gap_max[:m][has_gap], self.levels]
        parts_pos = [prev_pos[has_gap], self.pos_at_most]
        parts_neg = [(prev_neg + self.bucket[:m] - self.tied)[has_gap], neg_cum[:m]]
        if self.gap_max[m] > -np.inf:  # the last point, above every positive
            parts_t.append([self.gap_max[m]])
            parts_pos.append([self.n_pos])
            parts_neg.append([neg_cum[m]])
        first_is_negative = np.isfinite(self.neg_min) and (m == 0 or self.neg_min < self.levels[0])
        if first_is_negative and not (m and has_gap[0] and self.gap_max[0] == self.neg_min):
            parts_t.append([self.neg_min])  # the first point (unless it is gap 0's point)
            parts_pos.append([0])
            parts_neg.append([self.neg_min_count])
        thresholds = np.concatenate([np.asarray(t, dtype=np.float64) for t in parts_t])
        order = np.argsort(thresholds, kind="stable")  # thresholds are distinct
        thresholds = thresholds[order]
        counts = np.stack([np.concatenate([np.asarray(c, dtype=np.int64) for c in parts_pos]),
                           np.concatenate([np.asarray(c, dtype=np.int64) for c in parts_neg])],
                          axis=1)[order]
        tp = counts[:, 0] * self.weight
        fp = counts[:, 1] * self.weight
        denom = np.full(len(thresholds), int(denominator), dtype=np.int64)
        precision = tp / (tp + fp)
        with np.errstate(invalid="ignore", divide="ignore"):
            recall = np.where(denom > 0, tp / np.maximum(denom, 1), np.nan)
        return PRCurve(threshold=thresholds, precision=precision.astype(np.float64),
                       recall=recall.astype(np.float64), tp=tp, fp=fp, fn=denom - tp)


# ------------------------------------------------------------ protocol 2's positive pairs


@dataclass(frozen=True)
class PositivePredictions:
    """The positive predictions of protocol 2 as (query row, candidate column) pairs.

    For a symmetric descriptor each unordered positive pair ``i < j`` is one
    prediction read at row ``j``, column ``i`` (the lower triangle the block
    pass computes); otherwise both ordered pairs. Sorted by row, then column.
    """

    row: np.ndarray
    col: np.ndarray
    weight: int

    def in_rows(self, a: int, b: int) -> slice:
        """The predictions whose row is in ``[a, b)``."""
        return slice(int(np.searchsorted(self.row, a, "left")),
                     int(np.searchsorted(self.row, b, "left")))


def positive_predictions(pairs: np.ndarray, symmetric: bool) -> PositivePredictions:
    """Rows and columns of the positive predictions from ``(K, 2)`` unordered pairs ``i < j``."""
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    if symmetric:
        row, col = pairs[:, 1], pairs[:, 0]
    else:
        row = np.concatenate([pairs[:, 0], pairs[:, 1]])
        col = np.concatenate([pairs[:, 1], pairs[:, 0]])
    order = np.lexsort((col, row))
    return PositivePredictions(row[order], col[order], 2 if symmetric else 1)


def positive_values(descriptor, descriptors, positives: PositivePredictions,
                    chunk: int = POSITIVE_QUERY_CHUNK, count: bool = False):
    """float32 distances of the positive predictions, computed before the block pass.

    Queries are taken ``chunk`` distinct rows at a time against the union of
    their partners, so the cost is a small multiple of the positives' count.
    The values are rounded to float32, as the affinity stores them. With
    ``count`` the number of distances evaluated is returned as well.
    """
    out = np.empty(len(positives.row), dtype=np.float32)
    evaluated = 0
    rows = np.unique(positives.row)
    for start in range(0, len(rows), chunk):
        qs = rows[start : start + chunk]
        sel = positives.in_rows(int(qs[0]), int(qs[-1]) + 1)
        cols = np.unique(positives.col[sel])
        dist, _ = descriptor.pairwise(descriptors[qs], descriptors[cols])
        dist = np.asarray(dist, dtype=np.float64)
        evaluated += dist.size
        qi = np.searchsorted(qs, positives.row[sel])
        ci = np.searchsorted(cols, positives.col[sel])
        out[sel] = dist[qi, ci].astype(np.float32)
    return (out, evaluated) if count else out


# ---------------------------------------------------------------- the streamed block pass

#: how the affinity is kept: ``auto`` picks by size (below)
AFFINITY_STORAGE = ("auto", "float32", "float16", "decimated", "none")
#: ``auto`` keeps the full float32 matrix up to this many frames (64 MiB) ...
AUTO_FLOAT32_MAX_FRAMES = 4096
#: ... float16 up to this many (128 MiB), and a decimated float16 matrix beyond
AUTO_FLOAT16_MAX_FRAMES = 8192
#: side of the decimated matrix kept for figures (at most)
DECIMATED_SIDE = 4096
PR_COUNTING = ("exact, streamed: negatives counted between consecutive sorted positive "
               "distances, block by block (no N x N array)")


def resolve_storage(storage: str, n: int) -> str:
    """The concrete storage of an ``n``-frame affinity for ``storage`` (``auto`` by size)."""
    if storage not in AFFINITY_STORAGE:
        from lidar_iris_eval.errors import LirisError

        raise LirisError("affinity storage",
                         f"unknown value {storage!r}; choose from {', '.join(AFFINITY_STORAGE)}")
    if storage != "auto":
        return storage
    if n <= AUTO_FLOAT32_MAX_FRAMES:
        return "float32"
    return "float16" if n <= AUTO_FLOAT16_MAX_FRAMES else "decimated"


@dataclass(frozen=True)
class StreamedAffinity(Affinity):
    """The affinity of a streamed pass: what was kept of it, and how.

    Attributes (beyond :class:`~lidar_iris_eval.matching.blocks.Affinity`)
    ----------------------------------------------------------------------
    matrix : the full ``(N, N)`` affinity (float32 or float16, NaN diagonal),
        or None when not kept.
    decimated : every ``step``-th frame's rows and columns (float16), or None.
    step : frame step of ``decimated`` (1 when the full matrix is kept).
    storage : ``float32``, ``float16``, ``decimated`` or ``none``.
    passes : block passes made (2 only if a positive's batched distance
        differed from the one computed first).
    """

    decimated: np.ndarray | None = None
    step: int = 1
    storage: str = "float32"
    passes: int = 1

    def storage_note(self) -> str:
        """For metrics.json: which affinity was written, and why not the full one."""
        if self.storage in ("float32", "float16"):
            return f"full {self.storage}"
        if self.storage == "decimated":
            side = 0 if self.decimated is None else len(self.decimated)
            return (f"decimated float16 for figures: every {self.step}th frame "
                    f"({side} x {side}); metrics use every pair")
        return "not stored; metrics use every pair"


def count_block(acc: StreamingPR, pp: PositivePredictions, expected: np.ndarray,
                symmetric: bool, a: int, b: int, d32: np.ndarray) -> tuple[np.ndarray, bool]:
    """Count the negatives of one float32 block (rows ``[a, b)``) into ``acc``.

    The positives of the block are read out (and compared with ``expected``,
    their values computed beforehand), then masked together with the pairs the
    pass does not score (the diagonal; for a symmetric descriptor everything
    but the strict lower triangle). ``d32`` is overwritten. Returns the block's
    positive values and whether any differed from ``expected``.
    """
    sel = pp.in_rows(a, b)
    rows, cols = pp.row[sel] - a, pp.col[sel]
    got = d32[rows, cols]
    mismatch = not np.array_equal(got, expected[sel], equal_nan=True)
    d32[rows, cols] = np.nan
    if symmetric:  # only the strict lower triangle: column < row
        diag = d32[:, a:b]
        diag[np.triu_indices(b - a)] = np.nan
    else:
        d32[np.arange(b - a), np.arange(a, b)] = np.nan
    acc.add_negatives(d32)
    return got, mismatch


class CountNegatives:
    """Block-pass reducer (:class:`~lidar_iris_eval.matching.blocks.Reducer`): checks and
    masks each block's positives, counts its negatives into a :class:`StreamingPR`.

    Each part is a fresh accumulator of one block (exact integer sums and
    extrema), so a block computed in another process merges bit for bit.
    """

    timed = False

    def __init__(self, acc: StreamingPR, positives: PositivePredictions, expected: np.ndarray,
                 symmetric: bool):
        self.acc, self.pp, self.expected, self.symmetric = acc, positives, expected, symmetric
        self.gathered = np.empty_like(expected)
        self.mismatch = False

    def part(self, rows, d, y):
        a, b = int(rows[0]), int(rows[-1]) + 1
        acc = self.acc.fresh()
        got, mismatch = count_block(acc, self.pp, self.expected, self.symmetric, a, b,
                                    np.asarray(d).astype(np.float32))
        return a, b, acc, got, mismatch

    def merge(self, part) -> None:
        a, b, acc, got, mismatch = part
        self.acc.merge(acc)
        self.gathered[self.pp.in_rows(a, b)] = got
        self.mismatch |= bool(mismatch)


class KeepAffinity:
    """Block-pass reducer keeping the affinity :func:`stream_protocol2` was asked to keep
    (full float32 / float16, decimated float16 or none), from float32 blocks."""

    timed = False

    def __init__(self, symmetric: bool, n: int, storage: str):
        self.symmetric, self.n, self.storage = symmetric, n, storage
        self.matrix = None
        self.decimated = None
        self.step = 1
        if storage in ("float32", "float16"):
            self.matrix = np.empty((n, n), dtype=storage)
        elif storage == "decimated":
            self.step = max(1, -(-n // DECIMATED_SIDE))
            side = -(-n // self.step)
            self.decimated = np.full((side, side), np.nan, dtype=np.float16)

    def part(self, rows, d, y):
        return int(rows[0]), int(rows[-1]) + 1, d

    def merge(self, part) -> None:
        a, b, d = part
        self._store(a, b, np.asarray(d).astype(np.float32))

    def _store(self, a: int, b: int, d32: np.ndarray) -> None:
        if self.matrix is not None:
            if self.symmetric:
                from lidar_iris_eval.matching.blocks import _fill_symmetric

                _fill_symmetric(self.matrix, d32, a, b)
            else:
                self.matrix[a:b] = d32
        elif self.decimated is not None:
            k = self.step
            first = -(-a // k) * k
            rows = np.arange(first, b, k)
            if len(rows) == 0:
                return
            cols = np.arange(0, d32.shape[1], k)
            if self.symmetric:
                cols = cols[cols < first] if len(cols) else cols
                block = d32[np.ix_(rows - a, cols)].astype(np.float16)
                self.decimated[np.ix_(rows // k, cols // k)] = block
                self.decimated[np.ix_(cols // k, rows // k)] = block.T
                # pairs inside the row group (both in rows): read from the lower triangle
                for i, r in enumerate(rows):
                    for c in rows[:i]:
                        v = np.float16(d32[r - a, c])
                        self.decimated[r // k, c // k] = v
                        self.decimated[c // k, r // k] = v
            else:
                self.decimated[np.ix_(rows // k, cols // k)] = d32[np.ix_(rows - a, cols)]

    def finish(self) -> None:
        if self.matrix is not None:
            np.fill_diagonal(self.matrix, np.nan)
        if self.decimated is not None:
            np.fill_diagonal(self.decimated, np.nan)



def stream_protocol2(descriptor, descriptors, pairs: np.ndarray, n_positive_pairs: int,
                     exclude=None, pair_budget: int | None = None,
                     progress=None, storage: str = "auto", executor=None):
    """Protocol 2's exact curve (and protocol 1's matches) from one block pass.

    Parameters
    ----------
    descriptor, descriptors : the method and its stacked descriptors.
    pairs : ``(K, 2)`` unordered positive pairs ``i < j`` (``GroundTruth.pairs``).
    n_positive_pairs : the recall denominator (ordered positive pairs).
    exclude : protocol 1's E or per-query limits
        (:func:`~lidar_iris_eval.matching.blocks.query_limits`), to take its
        best matches from the same pass; None for protocol 2 only.
    storage : which affinity to keep (:data:`AFFINITY_STORAGE`).
    executor : a :mod:`lidar_iris_eval.executor` executor; it decides where
        the blocks run. One whose block tasks return reductions only
        (``returns_blocks()`` False: Dask) keeps no affinity. The metrics are
        the same bit for bit.

    Memory is O(N + positives) plus one block of distances and the kept
    affinity (none, decimated or full, per ``storage``).

    Returns
    -------
    (StreamedAffinity, PRCurve, BestMatches or None)
    """
    import time

    from lidar_iris_eval.errors import warn
    from lidar_iris_eval.matching.blocks import (
        DEFAULT_PAIR_BUDGET,
        BestInRow,
        block_pass,
        row_blocks,
    )

    budget = DEFAULT_PAIR_BUDGET if pair_budget is None else pair_budget
    n = len(descriptors)
    symmetric = bool(descriptor.symmetric)
    pp = positive_predictions(pairs, symmetric)
    if n >= 2:  # load compiled kernels before the clock (compilation is not matching cost)
        descriptor.pairwise(descriptors[:1], descriptors[:2])
    start = time.perf_counter()
    expected, pre_evaluations = positive_values(descriptor, descriptors, pp, count=True)
    pre_s = time.perf_counter() - start
    kind = resolve_storage(storage, n)
    if executor is not None and not executor.returns_blocks():  # reductions only come back
        if storage != "auto" and kind != "none" and n > 0:
            warn("protocol 2 on a Dask cluster", f"blocks return counts only; the {kind} "
                 "affinity is not kept (metrics are exact and complete)")
        kind = "none"
    blocks = row_blocks(n, budget, symmetric)
    count = CountNegatives(StreamingPR(expected, pp.weight), pp, expected, symmetric)
    keep = KeepAffinity(symmetric, n, kind)
    best = BestInRow(n, exclude) if exclude is not None else None  # (K, N): --convention-band
    reducers = ([keep] if kind != "none" else []) + [count] + ([best] if best else [])
    evaluations, seconds = block_pass(descriptor, descriptors, blocks, reducers, executor,
                                      progress)
    keep.finish()
    matches = best.result(seconds, evaluations, "affinity") if best is not None else None
    seconds, evaluations = seconds + pre_s, evaluations + pre_evaluations
    passes, acc = 1, count.acc
    if count.mismatch:  # batched numbers depend on the batch: redo with the pass's own values
        warn(f"{descriptor.name} protocol 2",
             "pairwise distances of the positive pairs differ between batch shapes; "
             "counting the negatives again against the block values (a second pass)")
        gathered = count.gathered.copy()
        second = CountNegatives(StreamingPR(gathered, pp.weight), pp, gathered, symmetric)
        more, again_s = block_pass(descriptor, descriptors, blocks, [second], executor)
        seconds, evaluations, passes, acc = (seconds + again_s, evaluations + more, 2,
                                             second.acc)
    affinity = StreamedAffinity(
        matrix=keep.matrix, seconds=seconds, n_evaluations=evaluations, symmetric=symmetric,
        decimated=keep.decimated, step=keep.step, storage=kind, passes=passes)
    return affinity, acc.curve(n_positive_pairs), matches
