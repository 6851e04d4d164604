"""ESF's per-pair reference loop: the L1 distance, written plainly."""

from __future__ import annotations

import numpy as np


def prepare(record, params=None) -> np.ndarray:
    """Per-frame preparation: the float64 histogram."""
    return np.asarray(record, dtype=np.float64)


def reference_distance(a, b, params=None) -> tuple[float, int]:
    """``(L1 distance, -1)``: ESF estimates no shift."""
    return float(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).sum()), -1
