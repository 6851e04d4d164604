"""M2DP's binning of every projection in one compiled pass (numba).

The NumPy route of :func:`.descriptor.signature_matrix` spends most of its
time not in the projections or the arc tangents but in a dozen element-wise
passes over ``(points, 64 planes)`` float32 arrays and a ``bincount`` of
7.8 M indices per KITTI scan. Here one loop takes the projections ``x, y``
and the angles ``theta`` (still computed by NumPy, so they are the same bits)
and does the rest per element with the same float32 operations in the same
order: ``sector = int32((theta + pi) * t/(2 pi))``, ``ring =
int32(sqrt(sqrt(x*x + y*y) * l*l/maxRho))``, both clipped, then a counter
increment. IEEE float32 arithmetic is the same in NumPy and in numba (no
fastmath), so the counts, hence the descriptor, are bitwise those of the
NumPy route (tested).
"""

from __future__ import annotations

import numba
import numpy as np


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
