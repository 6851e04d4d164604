"""OverlapTransformer's per-pair reference loop: the squared L2 of two vectors, written plainly.

The batched route is the Gram identity on a BLAS product
(:func:`~lidar_iris_eval.descriptors.vector_common.gram_pairwise`); this is the
sum of squared differences, so ``liris bench`` reports how far the two round
apart (a few 1e-15 for unit vectors) and the per-pair speed-up.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.descriptors.vector_common import vector_rows


def prepare(record, params=None) -> np.ndarray:
    """Per-frame preparation: the float64 vector."""
    return np.asarray(record, dtype=np.float64).reshape(-1)


def reference_distance(a, b, params=None) -> tuple[float, int]:
    """``(distance of the params' metric, -1)``: no shift is estimated. The plain
    difference is :func:`~lidar_iris_eval.descriptors.vector_common.vector_rows`, the
    kernel these methods used before the Gram route."""
    return float(vector_rows(a, b, getattr(params, "metric", "l2sq"))), -1
