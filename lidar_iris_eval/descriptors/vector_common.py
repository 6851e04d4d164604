"""Helpers shared by the fixed-length vector baselines (M2DP, ESF).

Both take raw points with the same input checks and compare descriptors by a
row-wise norm; keeping the block loop here means the single-pair and batched
paths of both run through one reduction, which is what makes them bitwise equal.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from lidar_iris_eval.errors import LirisError, warn

#: memory per block of query-vs-database differences
BLOCK_BYTES = 32 * 2**20


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
