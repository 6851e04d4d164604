"""M2DP's per-pair reference loop: the Euclidean distance, written plainly."""

from __future__ import annotations

import numpy as np


def prepare(record, params=None) -> np.ndarray:
    """Per-frame preparation: the float64 vector."""
    return np.asarray(record, dtype=np.float64)


def reference_distance(a, b, params=None) -> tuple[float, int]:
    """``(L2 distance, -1)``: M2DP estimates no shift."""
    return float(np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64))), -1
