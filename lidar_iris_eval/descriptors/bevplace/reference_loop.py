"""BEVPlace++'s per-pair reference loop: the squared L2 of two global vectors, written plainly.

Same formula as OverlapTransformer's (:mod:`..overlap_transformer.reference_loop`);
a BEVPlace++ record is a dict (global vector, keypoints, local features) or
the global vector itself.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.descriptors.overlap_transformer.reference_loop import reference_distance

__all__ = ["prepare", "reference_distance"]


def prepare(record, params=None) -> np.ndarray:
    """Per-frame preparation: the float64 global vector."""
    vec = record["global"] if isinstance(record, dict) else record
    return np.asarray(vec, dtype=np.float64).reshape(-1)
