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


@numba.njit(cache=True, nogil=True)
def raw_histogram(vox, idx, occupied, grid, sides, heron, angle_bins, bins):  # pragma: no cover
    """The ten histograms of ESF before weighting, ``(10 * bins,)`` float64, in one pass.

    Parameters
    ----------
    vox : (N, 3) integer voxel coordinates of the points (int8 keeps the
        random corner reads in cache: a KITTI scan's int64 coordinates are 2.9 MB)
    idx : (S, 3) int64 accepted triplets, in draw order
    occupied : (grid**3,) bool
    grid : int
    sides : (S, 3) float32 side lengths (12, 13, 23)
    heron : (S,) float32 squared Heron areas
    angle_bins : (S, 3) int64 folded angle bins (at p1, p3, p2)
    bins : int

    Notes
    -----
    Replaces the corner gather, :func:`trace_lines` over the ``3 S`` sides and
    the four ``np.bincount`` calls of :func:`.descriptor.esf_histogram_numpy`,
    which made ``3 S``-long temporaries (about 60 % of ESF's time). The result
    is bitwise that route's: the four histograms fill disjoint bins, each bin
    is accumulated in the same order as ``np.bincount`` does (triplet by
    triplet, angle by angle), the float32 expressions of D2, D3 and the mixed
    ratio are evaluated in float32 exactly as written there, and ``max`` does
    not depend on order (tested on real scans).
    """
    n = idx.shape[0]
    hist = np.zeros(10 * bins, dtype=np.float64)
    strides = np.array([grid * grid, grid, 1], dtype=np.int64)
    inside = np.empty((n, 3), dtype=np.int64)
    count = np.empty((n, 3), dtype=np.int64)
    length = np.empty(3, dtype=np.int64)
    signed = np.empty(3, dtype=np.int64)
    # sides in PCL's order: 1->2, 1->3, 2->3
    first = (0, 0, 1)
    second = (1, 2, 2)
    for i in range(n):
        for s in range(3):
            p = idx[i, first[s]]
            q = idx[i, second[s]]
            base = 0
            major = 1
            for a in range(3):
                d = np.int64(vox[q, a]) - np.int64(vox[p, a])
                length[a] = abs(d)
                signed[a] = -strides[a] if d < 0 else strides[a]
                base += np.int64(vox[p, a]) * strides[a]
                if length[a] > major:
                    major = length[a]
            # the closed form's floor((2*m*k + M - 1) / (2*M)) kept as a running
            # remainder: an axis steps (at most once) when its remainder passes 2*M
            denom = 2 * major
            r0 = major - 1
            r1 = major - 1
            r2 = major - 1
            flat = base
            hits = 0
            for _ in range(major):
                if occupied[flat]:
                    hits += 1
                r0 += 2 * length[0]
                if r0 >= denom:
                    r0 -= denom
                    flat += signed[0]
                r1 += 2 * length[1]
                if r1 >= denom:
                    r1 -= denom
                    flat += signed[1]
                r2 += 2 * length[2]
                if r2 >= denom:
                    r2 -= denom
                    flat += signed[2]
            inside[i, s] = hits
            count[i, s] = major
    half = np.float32(0.5)
    top = np.float32(bins - 1)
    d3_max = np.float32(0.0)
    d2_max = np.float32(0.0)
    for i in range(n):
        d3 = np.sqrt(np.sqrt(heron[i]))
        if i == 0 or d3 > d3_max:
            d3_max = d3
        for s in range(3):
            if (i == 0 and s == 0) or sides[i, s] > d2_max:
                d2_max = sides[i, s]
    for i in range(n):
        in_sum = inside[i, 0] + inside[i, 1] + inside[i, 2]
        count_sum = count[i, 0] + count[i, 1] + count[i, 2]
        if in_sum <= 21:
            tri = 1
        elif count_sum - in_sum < 4:
            tri = 0
        else:
            tri = 2
        # A3: angles at p1, p3, p2 weighted by the voxel count of the opposite side
        hist[tri * bins + angle_bins[i, 0]] += count[i, 2] / 32.0
        hist[tri * bins + angle_bins[i, 1]] += count[i, 0] / 32.0
        hist[tri * bins + angle_bins[i, 2]] += count[i, 1] / 32.0
        # D3: sqrt(area), binned against the largest sample
        d3 = np.sqrt(np.sqrt(heron[i]))
        hist[(3 + tri) * bins + np.int64(np.floor(d3 / d3_max * top + half))] += 1.0
    for i in range(n):
        for s in range(3):
            hits = inside[i, s]
            c = count[i, s]
            if hits >= c - 1:
                cls = 0
            elif hits <= 7:
                cls = 1
            else:
                cls = 2
            hist[(6 + cls) * bins + np.int64(np.floor(sides[i, s] / d2_max * top + half))] += 1.0
    for i in range(n):
        for s in range(3):
            hits = inside[i, s]
            c = count[i, s]
            if hits < c - 1 and hits > 7:  # mixed: fraction of occupied voxels
                ratio = np.float32(hits) / np.float32(c)
                hist[9 * bins + np.int64(np.floor(ratio * top + half))] += 1.0
    return hist


@numba.njit(cache=True, nogil=True)
def column_means(points):  # pragma: no cover - compiled
    """``points.astype(float64).mean(axis=0)`` of an ``(N, 3)`` array, without the copy.

    NumPy reduces axis 0 of a C-contiguous ``(N, 3)`` array row after row
    (no pairwise summation across rows), so summing the float64 rows in order
    and dividing by ``N`` gives its values bitwise (tested on real scans);
    the float64 copy and the strided reduction were 80 % of ``normalise``.
    """
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    for i in range(points.shape[0]):
        s0 += np.float64(points[i, 0])
        s1 += np.float64(points[i, 1])
        s2 += np.float64(points[i, 2])
    n = np.float64(points.shape[0])
    out = np.empty(3, dtype=np.float64)
    out[0] = s0 / n
    out[1] = s1 / n
    out[2] = s2 / n
    return out


@numba.njit(cache=True, nogil=True, error_model="numpy")
def triangle_geometry(points, idx):  # pragma: no cover - compiled
    """Sides, squared Heron area and the three cosines of each triplet, float32.

    The gather and the float32 maths of :func:`.descriptor._triangle_geometry`
    per triplet, with no ``(B, 3)`` temporaries (six of them, each a random
    gather or an ``einsum``): every value is formed in float32 in that
    function's order (an ``einsum`` dot product is ``0 + x0*y0 + x1*y1 +
    x2*y2``), so sides and areas are bitwise equal and the cosines are the
    ones its ``arccos`` receives (tested). Degenerate sides give inf/NaN as
    in NumPy (``error_model="numpy"``), and the triplet is redrawn.

    Parameters
    ----------
    points : (N, 3) float32, normalised
    idx : (B, 3) int64 triplets

    Returns
    -------
    sides : (B, 3) float32, sides 12, 13, 23
    heron : (B,) float32
    cosines : (B, 3) float32, at p1, p3, p2
    """
    n = idx.shape[0]
    sides = np.empty((n, 3), np.float32)
    heron = np.empty(n, np.float32)
    cosines = np.empty((n, 3), np.float32)
    zero = np.float32(0.0)
    half = np.float32(0.5)
    for i in range(n):
        i1, i2, i3 = idx[i, 0], idx[i, 1], idx[i, 2]
        v21x = points[i2, 0] - points[i1, 0]
        v21y = points[i2, 1] - points[i1, 1]
        v21z = points[i2, 2] - points[i1, 2]
        v31x = points[i3, 0] - points[i1, 0]
        v31y = points[i3, 1] - points[i1, 1]
        v31z = points[i3, 2] - points[i1, 2]
        v23x = points[i2, 0] - points[i3, 0]
        v23y = points[i2, 1] - points[i3, 1]
        v23z = points[i2, 2] - points[i3, 2]
        a = np.sqrt(zero + v21x * v21x + v21y * v21y + v21z * v21z)
        b = np.sqrt(zero + v31x * v31x + v31y * v31y + v31z * v31z)
        c = np.sqrt(zero + v23x * v23x + v23y * v23y + v23z * v23z)
        s = (a + b + c) * half
        heron[i] = s * (s - a) * (s - b) * (s - c)
        sides[i, 0] = a
        sides[i, 1] = b
        sides[i, 2] = c
        u21x, u21y, u21z = v21x / a, v21y / a, v21z / a
        u31x, u31y, u31z = v31x / b, v31y / b, v31z / b
        u23x, u23y, u23z = v23x / c, v23y / c, v23z / c
        cosines[i, 0] = zero + u21x * u31x + u21y * u31y + u21z * u31z
        cosines[i, 1] = zero + u23x * u31x + u23y * u31y + u23z * u31z
        cosines[i, 2] = zero + u23x * u21x + u23y * u21y + u23z * u21z
    return sides, heron, cosines
