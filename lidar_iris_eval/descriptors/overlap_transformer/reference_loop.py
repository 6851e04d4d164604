"""OverlapTransformer's per-pair reference loop: the squared L2 of two vectors, written plainly.

The batched route is the Gram identity on a BLAS product
(:func:`~lidar_iris_eval.descriptors.vector_common.gram_pairwise`); this is the
sum of squared differences, so ``liris bench`` reports how far the two round
apart (a few 1e-15 for unit vectors) and the per-pair speed-up.
"""

from __future__ import annotations

import numpy as np


def prepare(record, params=None) -> np.ndarray:
    """Per-frame preparation: the float64 vector."""
    return np.asarray(record, dtype=np.float64).reshape(-1)


def reference_distance(a, b, params=None) -> tuple[float, int]:
    """``(distance of the params' metric, -1)``: no shift is estimated."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    metric = getattr(params, "metric", "l2sq")
    if metric == "cosine":
        return float(1.0 - np.dot(a, b)), -1
    sq = float(np.sum((a - b) ** 2))
    return (sq if metric == "l2sq" else float(np.sqrt(sq))), -1
