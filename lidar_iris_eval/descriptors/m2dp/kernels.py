"""M2DP's compiled kernels (numba): the binning of every projection in one pass.

Two routes fill the ``(planes, l*t)`` vote counts:

* :func:`count_bins` (route ``atan2``) takes the float32 projections ``x, y``
  and ``theta = arctan2(y, x)`` computed by NumPy and does the rest per
  element with the same float32 operations in the same order as the NumPy
  reference (:func:`.descriptor.signature_matrix_numpy`): ``sector =
  int32((theta + pi) * t/(2 pi))``, ``ring = int32(sqrt(sqrt(x*x + y*y) *
  l*l/maxRho))``, both clipped, then a counter increment. IEEE float32
  arithmetic is the same in NumPy and in numba (no fastmath), so its counts
  are bitwise those of the NumPy route (tested).
* :func:`count_bins_compare` (route ``fast``, the default) starts from the raw
  points: it centres them, projects them with the PCA rotation folded into
  the plane axes, and finds both bin indices by comparisons instead of an arc
  tangent and two square roots. Ring ``k`` starts where ``x*x + y*y >=
  maxRho**2 * (k/l)**4`` (the squared edges), and the sector comes from the
  quadrant (signs of ``x``, ``y``) and the count of in-quadrant edges
  ``2*pi*j/t`` below the point (``|y| >= |x| * tan(2*pi*j/t)``), which
  needs ``t`` to be a multiple of 4. Every step is a multiply, add, compare
  or select, so the loop over points vectorises; it differs from the
  ``atan2`` route only for votes within float32 rounding of a bin edge (a
  handful of the 7.8 M votes of a KITTI scan; the tolerance is tested).

:func:`moments` gives the centroid, scatter matrix and largest squared radius
the ``fast`` route's PCA needs, in float64, in two passes over the points.
"""

from __future__ import annotations

import numba
import numpy as np

#: points per block of :func:`count_bins_compare`: the block's centred
#: coordinates and its (planes, block) bin indices stay in the L1 cache
#: next to the (planes, l*t) counters.
BLOCK = 128


@numba.njit(cache=True, nogil=True)
def count_bins(x, y, theta, pi32, theta_scale, rho_scale, t, r, counts):  # pragma: no cover
    """Add the bins of one chunk of projections to ``counts`` (``(planes, r*t)`` integers).

    Parameters
    ----------
    x, y, theta : (n, planes) float32
        In-plane coordinates and ``arctan2(y, x)`` of each point on each plane.
    pi32, theta_scale, rho_scale : float32
        ``pi``, ``t / (2 pi)`` and ``l**2 / maxRho``.
    t, r : int
        Sectors and rings.
    """
    n, planes = x.shape
    flat = np.empty(planes, dtype=np.int32)
    top_sector = np.int32(t - 1)
    top_ring = np.int32(r - 1)
    for i in range(n):
        xi, yi, ti = x[i], y[i], theta[i]
        for k in range(planes):  # branch-free, so it vectorises
            sector = min(np.int32((ti[k] + pi32) * theta_scale), top_sector)
            rho = np.sqrt(xi[k] * xi[k] + yi[k] * yi[k]) * rho_scale
            ring = min(np.int32(np.sqrt(rho)), top_ring)
            flat[k] = ring * np.int32(t) + sector
        for k in range(planes):
            counts[k, flat[k]] += 1


@numba.njit(cache=True, nogil=True)
def moments(points):  # pragma: no cover
    """Centroid, scatter matrix and largest squared distance to the centroid, in float64.

    Two passes (mean first, then the centred sums) keep the scatter as
    accurate as NumPy's ``centred.T @ centred`` for clouds far from the origin.

    Parameters
    ----------
    points : (N, 3+) float32 or float64 array, any strides

    Returns
    -------
    mean : (3,) float64
    scatter : (3, 3) float64
        ``sum((p - mean)(p - mean)^T)``.
    max_r2 : float
        ``max |p - mean|**2``.
    """
    n = points.shape[0]
    s0 = s1 = s2 = 0.0
    for i in range(n):
        s0 += np.float64(points[i, 0])
        s1 += np.float64(points[i, 1])
        s2 += np.float64(points[i, 2])
    m0, m1, m2 = s0 / n, s1 / n, s2 / n
    c00 = c01 = c02 = c11 = c12 = c22 = 0.0
    max_r2 = 0.0
    for i in range(n):
        a = points[i, 0] - m0
        b = points[i, 1] - m1
        c = points[i, 2] - m2
        c00 += a * a
        c01 += a * b
        c02 += a * c
        c11 += b * b
        c12 += b * c
        c22 += c * c
        max_r2 = max(max_r2, a * a + b * b + c * c)
    mean = np.array([m0, m1, m2])
    scatter = np.array([[c00, c01, c02], [c01, c11, c12], [c02, c12, c22]])
    return mean, scatter, max_r2


@numba.njit(cache=True, nogil=True, fastmath={"contract"})
def count_bins_compare(points, mean, ax, ay, tans, ring_edges2, t, counts,
                       flat):  # pragma: no cover
    """Add every point's bin on every plane to ``counts`` (``(planes, r*t)`` integers).

    Parameters
    ----------
    points : (N, 3+) float32 or float64 array, any strides
        Raw points; they are centred on ``mean`` and rounded to float32.
    mean : (3,) float64
    ax, ay : (3, planes) float32
        In-plane axes of each plane expressed in the sensor frame: the PCA
        axes times the plane axes, so ``x = (p - mean) @ ax``.
    tans : tuple of float32
        ``tan(2*pi*j/t)`` for ``j = 1 .. t/4 - 1``: the sector edges inside a
        quadrant (padded with ``inf`` when empty).
    ring_edges2 : tuple of float32
        ``maxRho**2 * (k/l)**4`` for ``k = 1 .. l - 1`` (padded with ``inf``).
    t : int
        Sectors, a multiple of 4.
    counts : (planes, l*t) int32 or int64
        Vote counters, added to.
    flat : (planes, BLOCK) uint16 or uint32
        Scratch for one block's flat counter indices; unsigned, so indexing
        ``counts`` needs no negative-index check (uint16 when
        ``counts.size <= 65536``, half the cache lines; both made the
        increments measurably faster than int32).

    Notes
    -----
    With ``q`` in-quadrant edges below the point, the sector is ``t/2 + q``
    for ``x > 0, y >= 0`` (angle in ``[0, pi/2)``), ``t - 1 - q`` for
    ``x <= 0, y >= 0``, ``q`` for ``x < 0, y < 0`` and ``t/2 - 1 - q`` for
    ``x >= 0, y < 0``, and ``t/2`` at ``x = y = 0`` (a degenerate plane, e.g.
    azimuth 0 at elevation 0, projects every point there): this is
    ``floor((atan2(y, x) + pi) * t / (2 pi))``, clipped, on the axes and at
    the origin too; only points exactly on an oblique edge (``|y| = |x| *
    tan``) may go to the neighbouring sector. Counts are kept as float32 until the flat
    index (exact below 2**24), which keeps the whole loop on 8-float vectors.
    ``fastmath`` only allows fused multiply-adds in the projections.
    """
    n = points.shape[0]
    planes = ax.shape[1]
    row_len = counts.shape[1]
    m0, m1, m2 = mean[0], mean[1], mean[2]
    centred = np.empty((3, BLOCK), dtype=np.float32)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    half = np.float32(t // 2)
    top = np.float32(t - 1)
    width = np.float32(t)
    votes = counts.ravel()
    for start in range(0, n, BLOCK):
        m = min(BLOCK, n - start)
        for i in range(m):
            centred[0, i] = np.float32(points[start + i, 0] - m0)
            centred[1, i] = np.float32(points[start + i, 1] - m1)
            centred[2, i] = np.float32(points[start + i, 2] - m2)
        cx, cy, cz = centred[0], centred[1], centred[2]
        for k in range(planes):
            a0, a1, a2 = ax[0, k], ax[1, k], ax[2, k]
            b0, b1, b2 = ay[0, k], ay[1, k], ay[2, k]
            offset = np.float32(k * row_len)
            row = flat[k]
            for i in range(m):  # branch-free: vectorises over points
                x = cx[i] * a0 + cy[i] * a1 + cz[i] * a2
                y = cx[i] * b0 + cy[i] * b1 + cz[i] * b2
                r2 = x * x + y * y
                ring = zero
                for edge in numba.literal_unroll(ring_edges2):
                    ring = ring + one if r2 >= edge else ring
                abs_x = max(x, -x)
                abs_y = max(y, -y)
                q = zero
                for tan in numba.literal_unroll(tans):
                    q = q + one if abs_y >= abs_x * tan else q
                upper = half + q if x > zero else top - q
                lower = half - one - q if x >= zero else q
                sector = upper if y >= zero else lower
                sector = half if r2 == zero else sector  # atan2(0, 0) = 0
                row[i] = offset + ring * width + sector  # exact: an integer below 2**24
        # votes point by point: the 64 planes' counters are distinct, so no
        # increment waits for the previous one (consecutive points of a scan
        # mostly fall in the same bin of a plane)
        for i in range(m):
            for k in range(planes):
                votes[flat[k, i]] += 1
