"""Revisit queries of a simulated route, for the summary line and the manifest.

Its own module so that writers of other frame kinds (push-broom swathes) count
revisits the way scans are counted without importing the pipeline that calls them.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def revisit_queries(positions: np.ndarray, exclude: int = 30, radius: float = 4.0) -> np.ndarray:
    """Indices i with some j <= i - ``exclude`` within ``radius`` (3-D distance)."""
    tree = cKDTree(positions)
    out = []
    for i, nbrs in enumerate(tree.query_ball_point(positions, radius)):
        if nbrs and min(nbrs) <= i - exclude:
            out.append(i)
    return np.asarray(out, dtype=np.int64)
