"""Compiled all-pairs distances of fixed-length vectors (M2DP's L2, ESF's L1), bitwise NumPy's.

The NumPy route (:func:`~lidar_iris_eval.descriptors.vector_common.pairwise_blocks`
with a broadcasting row kernel such as ``m2dp.l2_rows``) builds a ``(block, M, W)``
float64 difference, squares (or takes the absolute value of) it and sums the
last axis: 32 MiB temporaries written and read three times, on one core. For
KITTI 00 (10.3 M pairs) that was about 12 s for ESF and 3 s for M2DP.

:func:`pair_distances` computes every pair's value directly, without
temporaries, with the query rows split over threads (numba ``prange``). Its
sum is NumPy's own pairwise summation, step for step, so every value is
bitwise the NumPy route's:

* ``np.add.reduce`` along a contiguous axis of ``W`` float64 values (no
  initial value) adds NumPy's ``pairwise_sum`` of all ``W`` values to zero
  (``0.0 + s == s``);
* ``pairwise_sum(a, n)``: for ``n < 8`` a left-to-right sum from ``-0.0``;
  for ``n <= 128`` eight running sums ``r[j] = a[j] + a[j + 8] + ...`` over
  the first ``n - n % 8`` values, combined as
  ``((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))``, then the remaining
  values added left to right; above 128 the two halves at
  ``n2 = n // 2 - (n // 2) % 8``, each summed so, then added.

The element terms are the same IEEE operations as NumPy's (each operand
converted to float64, ``row - query``, then its square or absolute value), no
fast-math, no fused multiply-add. ``tests/test_vector_kernels.py`` checks the
values bitwise against the NumPy routes on random and real widths.
"""

from __future__ import annotations

import numba as nb
import numpy as np

#: metrics, as integers for the kernel
METRIC_L1, METRIC_L2SQ, METRIC_L2 = 0, 1, 2
METRICS = {"l1": METRIC_L1, "l2sq": METRIC_L2SQ, "l2": METRIC_L2}
#: NumPy's pairwise-summation block (``PW_BLOCKSIZE`` in its loops)
_PW_BLOCK = 128
#: fewer pairs than this are computed on the calling thread: a parallel launch must wait
#: for every numba thread to be scheduled, which on a loaded machine cost ~8 ms a call
#: (protocol 2 computes its positives in ~300 small calls)
PARALLEL_MIN_PAIRS = 1 << 16
#: queries per thread task and database rows per inner chunk: a chunk of the
#: database (64 x 640 float32 = 160 kB at most) is reused by the 8 queries
_TILE_Q = 8
_TILE_M = 64


def summation_plan(n: int) -> tuple[np.ndarray, np.ndarray]:
    """NumPy's pairwise summation of ``n`` values as leaves and a stack program.

    Returns ``leaves`` (L, 2) ``(start, length)`` in order, and ``program``: a
    post-order walk of the recursion where ``k >= 0`` pushes leaf ``k``'s sum
    and ``-1`` replaces the top two sums ``a, b`` (``b`` on top) by ``a + b``.
    """
    leaves: list[tuple[int, int]] = []
    program: list[int] = []

    def walk(lo: int, size: int) -> None:
        if size <= _PW_BLOCK:
            program.append(len(leaves))
            leaves.append((lo, size))
            return
        half = size // 2
        half -= half % 8
        walk(lo, half)
        walk(lo + half, size - half)
        program.append(-1)

    walk(0, n)
    return np.array(leaves, dtype=np.int64).reshape(-1, 2), np.array(program, dtype=np.int64)


@nb.njit(cache=True, nogil=True)
def _leaf_sum(t, lo, n):
    """NumPy's ``pairwise_sum`` of ``t[lo : lo + n]`` for ``n <= 128`` (no recursion)."""
    if n < 8:
        res = -0.0
        for k in range(lo, lo + n):
            res += t[k]
        return res
    r0, r1, r2, r3 = t[lo], t[lo + 1], t[lo + 2], t[lo + 3]
    r4, r5, r6, r7 = t[lo + 4], t[lo + 5], t[lo + 6], t[lo + 7]
    stop = lo + n - n % 8
    for k in range(lo + 8, stop, 8):
        r0 += t[k]
        r1 += t[k + 1]
        r2 += t[k + 2]
        r3 += t[k + 3]
        r4 += t[k + 4]
        r5 += t[k + 5]
        r6 += t[k + 6]
        r7 += t[k + 7]
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    for k in range(stop, lo + n):
        res += t[k]
    return res


@nb.njit(cache=True, nogil=True)
def _plan_sum(t, leaves, program, stack):
    """The pairwise sum of ``t`` by the plan of :func:`summation_plan`."""
    top = 0
    for step in program:
        if step >= 0:
            stack[top] = _leaf_sum(t, leaves[step, 0], leaves[step, 1])
            top += 1
        else:
            top -= 1
            stack[top - 1] = stack[top - 1] + stack[top]
    return stack[0]


@nb.njit(cache=True, nogil=True)
def _fill_rows(queries, database, metric, leaves, program, out, i0, i1, terms, stack):
    """Pairs of query rows ``[i0, i1)`` with every database row, into ``out``.

    Per pair the ``W`` terms go to ``terms`` (a plain vector loop), then
    they are summed by NumPy's plan; ``0.0 +`` the sum is the reduction's start.
    Database rows are walked in chunks, each reused by all the rows.
    """
    nd, width = database.shape
    for j0 in range(0, nd, _TILE_M):
        j1 = min(nd, j0 + _TILE_M)
        for i in range(i0, i1):
            q = queries[i]
            for j in range(j0, j1):
                r = database[j]
                if metric == METRIC_L1:
                    for k in range(width):
                        terms[k] = abs(r[k] - q[k])
                else:
                    for k in range(width):
                        d = r[k] - q[k]
                        terms[k] = d * d
                total = 0.0 + _plan_sum(terms, leaves, program, stack) if width else 0.0
                out[i, j] = np.sqrt(total) if metric == METRIC_L2 else total


@nb.njit(cache=True, nogil=True, parallel=True)
def _pair_block(queries, database, metric, leaves, program, out):
    """Every pair of float64 ``queries`` (Q, W) and ``database`` (M, W) into ``out`` (Q, M),
    tiles of query rows on numba's threads."""
    nq, width = queries.shape
    tiles = (nq + _TILE_Q - 1) // _TILE_Q
    for tile in nb.prange(tiles):
        i0 = tile * _TILE_Q
        _fill_rows(queries, database, metric, leaves, program, out, i0, min(nq, i0 + _TILE_Q),
                   np.empty(width), np.empty(len(program) + 1))


@nb.njit(cache=True, nogil=True)
def _pair_block_serial(queries, database, metric, leaves, program, out):
    """:func:`_pair_block` on this thread: the same code per pair, no parallel launch."""
    nq, width = queries.shape
    _fill_rows(queries, database, metric, leaves, program, out, 0, nq,
               np.empty(width), np.empty(len(program) + 1))


def pair_distances(queries: np.ndarray, database: np.ndarray, metric: str) -> np.ndarray:
    """``(Q, M)`` float64 distances of every query row to every database row.

    ``metric``: ``"l1"`` (ESF), ``"l2"`` (M2DP) or ``"l2sq"``; bitwise equal to
    the broadcast NumPy rows (``l1_rows``, ``l2_rows``,
    :func:`~lidar_iris_eval.descriptors.vector_common.vector_rows`). Rows of
    float32 are converted to float64 first, as NumPy converts them.
    """
    # float32 -> float64 is exact: the kernel then subtracts what NumPy subtracts
    q = np.ascontiguousarray(queries, dtype=np.float64)
    d = np.ascontiguousarray(database, dtype=np.float64)
    out = np.empty((len(q), len(d)), dtype=np.float64)
    if len(q) and len(d):
        leaves, program = summation_plan(q.shape[1])
        kernel = _pair_block if out.size >= PARALLEL_MIN_PAIRS else _pair_block_serial
        kernel(q, d, METRICS[metric], leaves, program, out)
    return out


def pairwise_with_nan_yaws(queries: np.ndarray, database: np.ndarray, metric: str
                           ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`pair_distances` and all-nan yaws: ``Descriptor.pairwise``'s answer for
    descriptors that estimate no yaw (as ``vector_common.pairwise_blocks`` returns)."""
    dists = pair_distances(queries, database, metric)
    return dists, np.full(dists.shape, np.nan)
