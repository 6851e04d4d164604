"""M2DP: multiview 2-D projection descriptor (He, Wang and Zhang, IROS 2016).

The cloud is mean-centred and rotated onto its principal axes, then projected
onto 64 planes (4 azimuths x 16 elevations). Each projection is binned into
8 rings x 16 sectors around the centroid; the 64 x 128 matrix of bin
fractions is summarised by its first left and right singular vectors, a
192-d unit-norm pair (``||d|| = sqrt(2)``). Two descriptors are compared by
the L2 distance, in ``[0, 2*sqrt(2)]``; yaw is not estimated.

This follows the authors' ``M2DP.m`` / ``CountVote2D.c`` and reproduces the
distances measured with it (KITTI 00 scans 94|95 0.0457, 94|198 0.2085,
198|199 0.0604, 94|94 turned 90 degrees 0.2296, turned 180 degrees 0.4293).

Sign rules
----------
* **PCA axes**: as MATLAB's ``pca``, each axis is flipped so that its
  largest-magnitude entry is positive. Axes are ordered by decreasing
  variance; the resulting frame may be a reflection (det = -1).
* **Singular vectors**: SVD fixes ``(u1, v1)`` only up to a common sign. The
  signature matrix is non-negative, so its leading singular vectors can be
  taken entrywise non-negative; ``svd_sign="positive"`` (default) flips the
  pair so that ``v1`` sums to a positive number. ``svd_sign="lapack"`` keeps
  whatever LAPACK returns, which is what the authors' code does (Octave and
  NumPy both usually return the all-negative pair); the L2 distance between
  two descriptors is the same under either rule whenever LAPACK is
  consistent, as it was on every shared scan.

Known weakness: rotation (reverse loops)
----------------------------------------
M2DP is *not* yaw invariant, although PCA alignment suggests it should be.
The sign rule above picks each axis' sign from the sensor-frame coordinate
that dominates it, so a yaw turn that changes the sign of that coordinate
flips the axis. On KITTI 00 scan 94, a turn of about 90 degrees negates the
second axis (the aligned cloud becomes a mirror image) and a turn of 180
degrees negates the first two (a half turn about the third axis). M2DP
is invariant to neither, so the same place scores 0.2296 (90 degrees) and
0.4293 (180 degrees) against itself, versus 0.2085 against an unrelated
place; a 33 degree turn, which flips no axis, scores 0. The authors' code
behaves identically. Consequently M2DP misses loops driven in the opposite
direction (e.g. KITTI 08), as reported in the LiDAR Iris paper. This is
expected behaviour of the method, kept on purpose for a faithful baseline.

Implementation notes
--------------------
Two routes compute the same signature (``M2DPParams.route``):

* ``fast`` (default, about 13 ms CPU per 120k-point KITTI scan on one
  core, 2.4x faster than ``atan2`` in the same run): one compiled pass gives
  the centroid and 3x3 scatter matrix, the PCA rotation is folded into the
  planes' axes (coinciding planes binned once), and one compiled loop
  projects every point in float32 and finds its ring and sector by
  comparisons against the squared ring edges and the sector edges of its
  quadrant (no arc tangent, no square root).
* ``atan2``: the previous release's computation, kept as the reference: a
  float64 aligned cloud, float32 projections and ``arctan2`` in chunks,
  the binning in numba (bitwise equal to the NumPy reference
  :func:`signature_matrix_numpy`, tested).

Both evaluate the projections in float32, so their bins differ from a
float64 evaluation, and from each other, only for points within float32
rounding of a bin edge: 0-4 of the 7.8 M votes of a shared KITTI scan,
descriptors within 3.1e-6 (tests/test_m2dp_routes.py states and enforces
the tolerance). Against a literal float64 reading of the authors' code the
``fast`` route moved 0-1 votes per shared scan, ``atan2`` 0-3.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.m2dp import kernels
from lidar_iris_eval.descriptors.vector_common import finite_xyz
from lidar_iris_eval.descriptors.vector_kernels import pairwise_with_nan_yaws
from lidar_iris_eval.errors import LirisError

_SVD_SIGNS = ("positive", "lapack")
_ROUTES = ("fast", "atan2")
#: points per chunk in the projection loop: keeps the (chunk, planes) work
#: arrays inside the CPU cache, which is what makes the NumPy path fast.
_CHUNK = 1024


@dataclass(frozen=True)
class M2DPParams:
    """Parameters of M2DP; the defaults are the paper's (p=4, q=16, t=16, l=8).

    Attributes
    ----------
    azimuths : int
        Number of plane azimuths ``p``, spread over ``[-pi/2, pi/2]``.
    elevations : int
        Number of plane elevations ``q``, spread over ``[0, pi/2]``.
    angular_bins : int
        Sectors per projection ``t``, equal slices of ``[-pi, pi]``.
    radial_bins : int
        Rings per projection ``l``; ring ``k`` ends at ``maxRho * ((k+1)/l)**2``.
    svd_sign : str
        ``"positive"`` (deterministic) or ``"lapack"`` (as returned by LAPACK).
    route : str
        How the signature is computed, not what it means. ``"fast"``
        (default): PCA from a compiled 3x3 scatter pass, rotation folded into
        the plane axes, bins by comparisons (:func:`signature_matrix_fast`).
        ``"atan2"``: the previous release's route, a float64 aligned cloud and
        float32 ``arctan2`` sectors (:func:`pca_align` +
        :func:`signature_matrix`), bitwise as before. The two differ only for
        votes within float32 rounding of a bin edge (tested tolerance). With
        ``angular_bins`` not a multiple of 4, ``"fast"`` uses ``"atan2"``.
    """

    azimuths: int = 4
    elevations: int = 16
    angular_bins: int = 16
    radial_bins: int = 8
    svd_sign: str = "positive"
    route: str = "fast"


def pca_align(points: np.ndarray) -> np.ndarray:
    """Centre ``points`` and express them on their principal axes.

    Axes are sorted by decreasing variance and signed as MATLAB's ``pca``
    does (largest-magnitude entry of each axis positive), so the result
    matches the reference code, including its rotation weakness.

    Parameters
    ----------
    points : (N, 3) array

    Returns
    -------
    (N, 3) float64 array of coordinates along the 1st, 2nd and 3rd axes.
    """
    centred = np.asarray(points, dtype=np.float64)
    centred = centred - centred.mean(axis=0)
    return centred @ principal_axes(centred.T @ centred)


def principal_axes(scatter: np.ndarray) -> np.ndarray:
    """``(3, 3)`` principal axes (columns) of a scatter matrix, signed as MATLAB's ``pca``.

    The 3x3 scatter matrix has the same eigenvectors as the SVD of the data
    that MATLAB uses, at a fraction of the cost for 120k points. Columns are
    sorted by decreasing variance, each flipped so that its largest-magnitude
    entry is positive. Both routes use this one rule.
    """
    _, vectors = np.linalg.eigh(scatter)
    axes = vectors[:, ::-1]
    dominant = np.argmax(np.abs(axes), axis=0)
    return axes * np.where(axes[dominant, np.arange(3)] < 0, -1.0, 1.0)


def projection_planes(azimuths: int, elevations: int) -> tuple[np.ndarray, np.ndarray]:
    """In-plane axes ``(px, py)`` of every projection plane, each ``(3, p*q)``.

    Planes are ordered azimuth-major (the reference's outer loop). ``px`` is
    the x axis minus its component along the normal, deliberately *not*
    normalised (as in the reference, it scales each projection by
    ``sqrt(1 - n_x**2)``); ``py = n x px``.
    """
    az, el = np.meshgrid(
        np.linspace(-np.pi / 2, np.pi / 2, azimuths),
        np.linspace(0.0, np.pi / 2, elevations),
        indexing="ij",
    )
    az, el = az.ravel(), el.ravel()
    normals = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
    px = np.array([1.0, 0.0, 0.0]) - normals[:, :1] * normals
    py = np.cross(normals, px)
    return px.T, py.T


def _projection_setup(aligned: np.ndarray, params: M2DPParams):
    """What both binning routes share: float32 points and plane axes, and the bin scales.

    Kept in one place so the compiled route and its NumPy reference cannot
    drift apart in the float32 constants their bitwise equality depends on.
    """
    t, r = params.angular_bins, params.radial_bins
    px, py = projection_planes(params.azimuths, params.elevations)
    max_rho = float(np.sqrt(np.max(np.einsum("ij,ij->i", aligned, aligned))))
    if not max_rho > 0.0:
        raise LirisError("points", "M2DP needs points that are not all identical")
    pts = np.asarray(aligned, dtype=np.float32)
    theta_scale = np.float32(t / (2 * np.pi))
    rho_scale = np.float32(r * r / max_rho)
    return (pts, px.astype(np.float32), py.astype(np.float32), theta_scale,
            np.float32(np.pi), rho_scale)


def signature_matrix(aligned: np.ndarray, params: M2DPParams) -> np.ndarray:
    """The ``(p*q, l*t)`` matrix of bin fractions: one row per plane, column ``r*t + s``
    for ring ``r`` and sector ``s``.

    Parameters
    ----------
    aligned : (N, 3) array
        PCA-aligned points (:func:`pca_align`).
    params : M2DPParams

    Notes
    -----
    A point goes to the first bin whose upper edge exceeds it, overflow to
    the last, as ``CountVote2D.c``. With sector edges at ``-pi + 2*pi*k/t``
    and ring edges at ``maxRho*(k/l)**2``, the bin indices are
    ``floor((theta + pi) * t / (2*pi))`` and ``floor(l * sqrt(rho/maxRho))``,
    clipped, which avoids a search over edges.
    """
    t, r = params.angular_bins, params.radial_bins
    pts, px32, py32, theta_scale, pi32, rho_scale = _projection_setup(aligned, params)
    n_planes = px32.shape[1]
    # int32 counters fit the L1 cache (twice as fast as int64); exact below 2**31 points
    counts = np.zeros((n_planes, t * r), dtype=np.int32 if len(pts) < 2**31 else np.int64)
    for start in range(0, len(pts), _CHUNK):
        chunk = pts[start : start + _CHUNK]
        x, y = chunk @ px32, chunk @ py32
        kernels.count_bins(x, y, np.arctan2(y, x), pi32, theta_scale, rho_scale, t, r, counts)
    return counts / len(pts)


def signature_matrix_numpy(aligned: np.ndarray, params: M2DPParams) -> np.ndarray:
    """The NumPy route of :func:`signature_matrix` (its bitwise reference, tested)."""
    t, r = params.angular_bins, params.radial_bins
    pts, px32, py32, theta_scale, pi32, rho_scale = _projection_setup(aligned, params)
    n_planes = px32.shape[1]
    offsets = (np.arange(n_planes, dtype=np.int32) * (t * r))[None, :]
    counts = np.zeros(n_planes * t * r, dtype=np.int64)
    for start in range(0, len(pts), _CHUNK):
        chunk = pts[start : start + _CHUNK]
        x, y = chunk @ px32, chunk @ py32
        theta = np.arctan2(y, x)
        theta += pi32
        theta *= theta_scale
        sector = theta.astype(np.int32)
        np.minimum(sector, t - 1, out=sector)
        # ring index floor(l*sqrt(rho/maxRho)) = floor(sqrt(sqrt(x^2+y^2) * l^2/maxRho))
        x *= x
        y *= y
        x += y
        np.sqrt(x, out=x)
        x *= rho_scale
        np.sqrt(x, out=x)
        ring = x.astype(np.int32)
        np.minimum(ring, r - 1, out=ring)
        ring *= t
        ring += sector
        ring += offsets
        counts += np.bincount(ring.ravel(), minlength=counts.size)
    return counts.reshape(n_planes, t * r) / len(pts)


def fast_route_applies(params: M2DPParams) -> bool:
    """True when :func:`signature_matrix_fast` can bin with ``params``.

    It needs ``t`` a multiple of 4 (quadrant symmetry of the sector edges)
    and fewer than 2**24 counters (flat indices are formed in float32).
    """
    p = params
    cells = p.azimuths * p.elevations * p.angular_bins * p.radial_bins
    return p.route == "fast" and p.angular_bins % 4 == 0 and cells <= 2**24


def signature_matrix_fast(points: np.ndarray, params: M2DPParams,
                          merge_planes: bool = True) -> np.ndarray:
    """The signature of raw ``points`` by the ``fast`` route (see :class:`M2DPParams`).

    Same meaning as ``signature_matrix(pca_align(points), params)``; the
    votes differ only within float32 rounding of a bin edge (tested on random
    clouds and the real scans). Instead of building the aligned float64 cloud,
    one compiled pass takes the centroid and scatter matrix, the PCA rotation
    is folded into the planes' axes (``x = (p - mean) @ (axes @ px)``), and
    :func:`.kernels.count_bins_compare` bins each projection by comparisons
    against the squared ring edges and the in-quadrant sector edges.

    Parameters
    ----------
    points : (N, 3+) float32 or float64 array
        Finite points in the sensor frame (extra columns ignored).
    params : M2DPParams
        Must pass :func:`fast_route_applies` (its ``route`` is not looked at).
    merge_planes : bool
        Bin planes whose float32 axes coincide once (same votes, bitwise;
        ``False`` bins every plane, for the test that checks it).
    """
    t, r = params.angular_bins, params.radial_bins
    if not fast_route_applies(replace(params, route="fast")):
        raise ValueError(f"the fast route needs angular_bins divisible by 4 and at most 2**24 "
                         f"counters, got {params}")
    mean, scatter, max_r2 = kernels.moments(points)
    if not max_r2 > 0.0:
        raise LirisError("points", "M2DP needs points that are not all identical")
    axes = principal_axes(scatter)
    px, py = projection_planes(params.azimuths, params.elevations)
    # Planes whose float32 axes coincide vote identically: bin each once. (The
    # elevation-90 degree planes of every azimuth share the normal +z: 61 of 64.)
    both = np.vstack([axes @ px, axes @ py]).astype(np.float32)
    if merge_planes:
        unique, first, inverse = np.unique(both, axis=1, return_index=True, return_inverse=True)
    else:
        unique, first, inverse = both, np.arange(both.shape[1]), np.arange(both.shape[1])
    order = np.argsort(first)  # keep the planes in their order: same memory walk
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    both = np.ascontiguousarray(unique[:, order])
    ax, ay = both[:3], both[3:]
    # ring k starts at maxRho * (k/l)**2, so at maxRho**2 * (k/l)**4 in squared radius
    inf = (np.float32(np.inf),)
    ring_edges2 = tuple(np.float32(max_r2 * (k / r) ** 4) for k in range(1, r)) or inf
    tans = tuple(np.float32(np.tan(2 * np.pi * j / t)) for j in range(1, t // 4)) or inf
    counts = np.zeros((ax.shape[1], t * r), dtype=np.int32 if len(points) < 2**31 else np.int64)
    flat = np.empty((ax.shape[1], kernels.BLOCK),
                    dtype=np.uint16 if counts.size <= 2**16 else np.uint32)
    kernels.count_bins_compare(points, mean, ax, ay, tans, ring_edges2, t, counts, flat)
    return counts[rank[inverse.ravel()]] / len(points)


def descriptor_from_signature(signature: np.ndarray, svd_sign: str = "positive") -> np.ndarray:
    """``[u1; v1]``: first left and right singular vectors of the signature."""
    u, _, vt = np.linalg.svd(signature, full_matrices=False)
    desc = np.concatenate([u[:, 0], vt[0]])
    if svd_sign == "positive" and vt[0].sum() < 0:
        desc = -desc
    return desc


def l2_rows(query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """L2 distance of ``query`` to each row of ``rows`` (any leading shape).

    Single-pair, batched and pairwise distances all go through this one
    reduction along a contiguous last axis, so they agree bit for bit.
    """
    diff = np.asarray(rows, dtype=np.float64) - np.asarray(query, dtype=np.float64)
    diff *= diff
    return np.sqrt(np.sum(diff, axis=-1))


class M2DP(Descriptor):
    """M2DP global descriptor: 192-d, L2 distance, no yaw.

    See the module docstring for the sign rules and the documented failure
    on rotated (reverse) revisits.
    """

    name = "m2dp"
    label = "M2DP"
    color = "#009E73"
    params_type = M2DPParams
    per_frame = True  # each scan's descriptor is computed from that scan alone
    symmetric = True  # (a-b)**2 == (b-a)**2 exactly in IEEE arithmetic

    def __init__(self, params: M2DPParams | None = None, preset: str = "custom"):
        super().__init__(params, preset)
        p = self.params
        source = f"m2dp preset {preset}"
        for key in ("azimuths", "elevations", "angular_bins", "radial_bins"):
            if getattr(p, key) < 1:
                raise LirisError(source, f"{key} must be a positive integer, got {getattr(p, key)}")
        if p.svd_sign not in _SVD_SIGNS:
            raise LirisError(
                source, f"svd_sign must be one of {', '.join(_SVD_SIGNS)}, got {p.svd_sign!r}"
            )
        if p.route not in _ROUTES:
            raise LirisError(source, f"route must be one of {', '.join(_ROUTES)}, got {p.route!r}")

    @property
    def size(self) -> int:
        """Length of the descriptor: ``p*q + l*t``."""
        p = self.params
        return p.azimuths * p.elevations + p.angular_bins * p.radial_bins

    def compute(self, points: np.ndarray) -> np.ndarray:
        """Describe one scan: ``(N, 3)`` points to a ``(p*q + l*t,)`` float64 vector."""
        if fast_route_applies(self.params):
            # float32 scans stay float32 (a strided view, no copy): the route centres in float64
            dtype = np.float32 if np.asarray(points).dtype == np.float32 else np.float64
            pts = finite_xyz(points, minimum=3, dtype=dtype, method="M2DP")
            signature = signature_matrix_fast(pts, self.params)
        else:
            pts = finite_xyz(points, minimum=3, method="M2DP")
            signature = signature_matrix(pca_align(pts), self.params)
        return descriptor_from_signature(signature, self.params.svd_sign)

    def distance(self, query: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        """L2 distance (``[0, 2*sqrt(2)]``) and ``nan`` yaw."""
        return float(l2_rows(query, np.asarray(candidate)[None, :])[0]), float("nan")

    def distances(self, query: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M,)`` L2 distances of ``query`` to each database row, and nan yaws."""
        dists = l2_rows(query, database).reshape(len(database))
        return dists, np.full(len(database), np.nan)

    def pairwise(self, queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Q, M)`` L2 distances, each bitwise :func:`l2_rows`'s."""
        # compiled, on every numba thread (tests/test_vector_kernels.py)
        return pairwise_with_nan_yaws(queries, database, "l2")
