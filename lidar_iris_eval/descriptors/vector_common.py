"""Helpers shared by the fixed-length vector descriptors (M2DP, ESF, the learned ones).

M2DP and ESF take raw points with the same input checks and compare
descriptors by a row-wise norm; keeping the block loop here means the
single-pair and batched paths of both run through one reduction, which is what
makes them bitwise equal.

The learned descriptors (8192-d BEVPlace++, 256-d OverlapTransformer) compare
through :func:`gram_pairwise` instead: ``|q|^2 + |r|^2 - 2 q.r`` with the cross
term one BLAS matrix product, 70-90x faster than the broadcast difference at
8192-d (docs/performance.md). Its routes stay bitwise equal by always
calling the product on a padded shape (see :func:`gram_pairwise`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lidar_iris_eval.errors import LirisError, warn

#: memory per block of query-vs-database differences
BLOCK_BYTES = 32 * 2**20
#: rows of queries / database converted to float64 per matrix product (bounds memory:
#: 1024 x 8192 float64 is 64 MiB); the split never changes a value
GRAM_QUERY_ROWS = 256
GRAM_DATABASE_ROWS = 1024
#: every product is padded (zero rows) to multiples of GRAM_TILE rows and to at
#: least this many multiply-adds: OpenBLAS rounds one-row products and small ones
#: (measured: M N K up to about 1e6) differently from large ones; above it an entry's
#: value did not depend on the shape, position or subset it came in (4x margin)
GRAM_MIN_MNK = 1 << 22
GRAM_TILE = 8


def finite_xyz(points: np.ndarray, minimum: int, dtype=np.float64,
               method: str = "descriptor") -> np.ndarray:
    """The ``(N, 3)`` xyz of ``points`` in ``dtype`` with non-finite rows dropped.

    Raises LirisError for a wrong shape or fewer than ``minimum`` finite
    points; warns when rows are dropped.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise LirisError("points", f"expected an (N, 3) array, got shape {pts.shape}")
    pts = np.asarray(pts[:, :3], dtype=dtype)
    # one flat reduction in the usual all-finite case (a row-wise all() costs 2 ms per scan)
    if not np.isfinite(pts).all():
        finite = np.isfinite(pts).all(axis=1)
        warn("points", f"dropped {int((~finite).sum())} non-finite point(s)")
        pts = pts[finite]
    if len(pts) < minimum:
        raise LirisError("points", f"{method} needs at least {minimum} finite points, "
                         f"got {len(pts)}")
    return pts


def pairwise_blocks(kernel: Callable[[np.ndarray, np.ndarray], np.ndarray],
                    queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Q, M)`` distances from a broadcasting row kernel, in memory-bounded blocks.

    Yaws are all nan: these descriptors do not estimate one.
    """
    queries = np.asarray(queries)
    database = np.asarray(database)
    n_q, n_m = len(queries), len(database)
    out = np.empty((n_q, n_m), dtype=np.float64)
    width = database[0].size if n_m else 1
    block = max(1, BLOCK_BYTES // max(1, 8 * n_m * width))
    for start in range(0, n_q, block):
        q = queries[start : start + block]
        out[start : start + len(q)] = kernel(q[:, None, :], database[None, :, :])
    return out, np.full((n_q, n_m), np.nan)


def vector_rows(query: np.ndarray, rows: np.ndarray, metric: str = "l2sq") -> np.ndarray:
    """Distance of ``query`` to each row of ``rows`` (any leading shape), in float64.

    The single-pair, batched and pairwise distances all reduce through this, so
    they agree bit for bit. ``metric``: ``"l2sq"`` (faiss' ``IndexFlatL2``, what the
    learned methods' authors rank with), ``"l2"`` or ``"cosine"`` (``1 - q . r``, for
    unit vectors).
    """
    q = np.asarray(query, dtype=np.float64)
    r = np.asarray(rows, dtype=np.float64)
    if metric == "cosine":
        return 1.0 - np.sum(q * r, axis=-1)
    diff = r - q
    diff *= diff
    sq = np.sum(diff, axis=-1)
    return sq if metric == "l2sq" else np.sqrt(sq)


def _round_up(n: int, step: int) -> int:
    return -(-int(n) // step) * step


def gram_shape(n_q: int, n_m: int, width: int) -> tuple[int, int]:
    """The padded ``(rows, columns)`` of one product of ``n_q`` by ``n_m`` rows of ``width``:
    multiples of :data:`GRAM_TILE` with ``rows * columns * width >= GRAM_MIN_MNK``.

    Short sides grow first, and two short ones to a square (a single pair of
    256-d vectors is a 128 x 128 product, not 8 x 2048: less memory to zero).
    """
    width = max(1, int(width))
    rows, cols = _round_up(max(n_q, 1), GRAM_TILE), _round_up(max(n_m, 1), GRAM_TILE)
    need = -(-GRAM_MIN_MNK // width)  # rows * cols at least
    if rows * cols >= need:
        return rows, cols
    side = _round_up(np.ceil(np.sqrt(need)), GRAM_TILE)
    if rows < side and cols < side:
        rows = side
    if rows <= cols:
        rows = max(rows, _round_up(-(-need // cols), GRAM_TILE))
    else:
        cols = max(cols, _round_up(-(-need // rows), GRAM_TILE))
    return rows, cols


def _padded64(x: np.ndarray, rows: int) -> np.ndarray:
    """``x`` in float64 with zero rows appended up to ``rows`` (one copy, converting)."""
    out = np.empty((rows, x.shape[1]), dtype=np.float64)
    out[: len(x)] = x
    out[len(x):] = 0.0
    return out


def gram_pairwise(queries: np.ndarray, database: np.ndarray, metric: str = "l2sq"
                  ) -> np.ndarray:
    """``(Q, M)`` float64 distances of two stacks of vectors through one matrix product.

    ``l2sq`` is ``max(0, (|q|^2 - 2 q.r) + |r|^2)``, ``l2`` its root and
    ``cosine`` ``1 - q.r`` (unit vectors), all in float64; the squared norms are
    row-wise sums, the cross term a float64 BLAS product of zero-padded blocks
    (:func:`gram_shape`), so one pair's value is the same whichever block or route
    (single, batched, pairwise) computed it (with OpenBLAS, measured; another BLAS
    may differ, and protocol 2's streamed count then detects it and counts again).
    It differs from the broadcast difference (:func:`vector_rows`) by rounding
    only: at most a few 1e-15 for unit vectors (tests/test_learned_gram.py bounds
    it, with the rankings).
    """
    q = np.asarray(queries)
    d = np.asarray(database)
    n_q, n_m = len(q), len(d)
    out = np.empty((n_q, n_m), dtype=np.float64)
    if n_q == 0 or n_m == 0:
        return out
    width = q.shape[1]
    if d.shape[1] != width:
        raise LirisError("descriptors", f"query width {width} != database width {d.shape[1]}")
    for a in range(0, n_q, GRAM_QUERY_ROWS):
        n_a = min(GRAM_QUERY_ROWS, n_q - a)
        padded_q: dict[int, np.ndarray] = {}
        for b in range(0, n_m, GRAM_DATABASE_ROWS):
            n_b = min(GRAM_DATABASE_ROWS, n_m - b)
            rows, cols = gram_shape(n_a, n_b, width)
            if rows not in padded_q:
                padded_q = {rows: _padded64(q[a : a + n_a], rows)}
            qp, dp = padded_q[rows], _padded64(d[b : b + n_b], cols)
            cross = (qp @ dp.T)[:n_a, :n_b]
            block = out[a : a + n_a, b : b + n_b]
            if metric == "cosine":
                np.subtract(1.0, cross, out=block)
                continue
            qa, db = qp[:n_a], dp[:n_b]
            np.multiply(cross, -2.0, out=block)
            block += np.add.reduce(qa * qa, axis=1)[:, None]
            block += np.add.reduce(db * db, axis=1)[None, :]
            np.maximum(block, 0.0, out=block)
            if metric == "l2":
                np.sqrt(block, out=block)
    return out
