"""ESF's line tracing in one compiled loop (numba).

:func:`.descriptor.trace_lines_numpy` evaluates every step of every traced
side at once with ``np.repeat`` arrays (about 2 M voxel visits per KITTI
scan, a dozen temporaries of that length); that was 60 % of ESF's
extraction. This loop walks the same closed form of PCL's Bresenham steps,
``floor((2*m*k + M - 1) / (2*M))`` voxels along an axis of length ``m``
after ``k`` major steps, in integer arithmetic, so the counts are exactly
the NumPy route's (tested).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def trace_lines(start, end, occupied, grid):  # pragma: no cover - compiled
    """Occupied voxels visited and voxels visited, per line: two ``(L,)`` int64.

    Parameters
    ----------
    start, end : (L, 3) int64 voxel coordinates
    occupied : (grid**3,) bool
    grid : int
        Voxels per axis (strides ``grid**2, grid, 1``).
    """
    n = start.shape[0]
    inside = np.zeros(n, dtype=np.int64)
    count = np.empty(n, dtype=np.int64)
    strides = np.array([grid * grid, grid, 1], dtype=np.int64)
    length = np.empty(3, dtype=np.int64)
    signed = np.empty(3, dtype=np.int64)
    for i in range(n):
        base = 0
        major = 1
        for a in range(3):
            d = end[i, a] - start[i, a]
            length[a] = abs(d)
            signed[a] = -strides[a] if d < 0 else strides[a]
            base += start[i, a] * strides[a]
            if length[a] > major:
                major = length[a]
        count[i] = major
        denom = 2 * major
        hits = 0
        for k in range(major):
            flat = base
            for a in range(3):
                flat += (2 * length[a] * k + major - 1) // denom * signed[a]
            if occupied[flat]:
                hits += 1
        inside[i] = hits
    return inside, count


@numba.njit(cache=True, nogil=True)
def voxel_coords(points, half, grid):  # pragma: no cover - compiled
    """PCL's voxel index per coordinate (see :func:`.descriptor.voxel_coords`), one pass.

    ``floor``/``ceil`` of a float32 are exact, so this equals the NumPy route bitwise.
    """
    n = points.shape[0]
    out = np.empty((n, 3), dtype=np.int64)
    for i in range(n):
        for a in range(3):
            x = points[i, a]
            v = np.floor(x) + half if x < 0 else np.ceil(x) + (half - 1)
            if v < 0:
                v = 0
            elif v > grid - 1:
                v = grid - 1
            out[i, a] = np.int64(v)
    return out


@numba.njit(cache=True, nogil=True)
def centred_scaled(points, mean, half):  # pragma: no cover - compiled
    """``(points - mean) * (half / max_dist)`` as float32, and ``max_dist``.

    ``points`` (N, 3) float32 or float64, ``mean`` (3,) float64; every value is
    formed in float64 in NumPy's order (``sqrt(max(c0*c0 + c1*c1 + c2*c2))``),
    so the result equals the NumPy route of ``normalise`` bitwise (tested).
    Returns an empty array when ``max_dist`` is not positive.
    """
    n = points.shape[0]
    best = 0.0
    for i in range(n):
        c0 = np.float64(points[i, 0]) - mean[0]
        c1 = np.float64(points[i, 1]) - mean[1]
        c2 = np.float64(points[i, 2]) - mean[2]
        sq = c0 * c0 + c1 * c1 + c2 * c2
        if sq > best:
            best = sq
    max_dist = np.sqrt(best)
    out = np.empty((n if max_dist > 0.0 else 0, 3), np.float32)
    if max_dist > 0.0:
        scale = half / max_dist
        for i in range(n):
            for j in range(3):
                out[i, j] = np.float32((np.float64(points[i, j]) - mean[j]) * scale)
    return out, max_dist
