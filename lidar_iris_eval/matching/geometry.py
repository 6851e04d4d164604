"""Geometric tools shared by methods that verify a loop with a rigid fit.

GOSMatch, ESM and any segment/object method do the same three things after
retrieval: pair up features of two scans (nearest neighbours), fit a rigid
transform to the pairs robustly (RANSAC or PROSAC around a Kabsch fit), and
report how wrong a pose is. They live here once so that every method uses the
same, tested implementation and its results are comparable.

Conventions
-----------
* A pose is a ``(4, 4)`` float64 homogeneous matrix ``T`` acting on column
  vectors: ``p_dst = T[:3, :3] @ p_src + T[:3, 3]``.
* :func:`kabsch` and the robust fits return the ``T`` that maps ``src`` onto
  ``dst``. For loop closure, ``src`` are points (or feature positions) of the
  candidate scan and ``dst`` those of the query scan, so ``T`` maps the
  candidate's LiDAR frame into the query's LiDAR frame (the convention of
  ``matches.csv``).
* Randomised functions take an explicit ``numpy.random.Generator``; the same
  generator state and inputs give the same result, bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

#: hypotheses evaluated per vectorised batch (bounds memory to ~batch * n floats)
_BATCH = 256
#: dimension above which nearest neighbours use brute force rather than a k-d tree
_KDTREE_MAX_DIM = 16


# --------------------------------------------------------------------------- poses


def yaw_pose(yaw_deg: float, translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Rotation by ``yaw_deg`` counter-clockwise about +z, as a ``(4, 4)`` pose.

    ``translation`` fills the last column; pass ``(nan, nan, nan)`` for a
    yaw-only estimate whose translation is unknown.
    """
    a = np.deg2rad(float(yaw_deg))
    c, s = np.cos(a), np.sin(a)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = np.asarray(translation, dtype=np.float64)
    return T


def yaw_deg_of(T: np.ndarray) -> np.ndarray:
    """Heading (degrees, in ``(-180, 180]``) of the rotation part of pose(s) ``T``.

    The z angle of a z-y-x Euler decomposition: ``atan2(R[1, 0], R[0, 0])``,
    which is exact for a pure yaw and the heading of the x axis otherwise.
    """
    T = np.asarray(T, dtype=np.float64)
    return np.rad2deg(np.arctan2(T[..., 1, 0], T[..., 0, 0]))


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid pose(s) ``(..., 4, 4)`` using ``R^T`` (no general inverse)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply pose ``T`` to ``(n, 3)`` points."""
    points = np.asarray(points, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    """The rotation (in SO(3)) nearest to matrix/matrices ``R`` ``(..., 3, 3)``.

    The SVD projection ``U diag(1, 1, det(U V^T)) V^T``: it removes the scale
    and shear that printing a rotation to a few digits adds. Only finite
    matrices are projected; any with a NaN or inf come back as all NaN.
    """
    R = np.asarray(R, dtype=np.float64)
    out = np.full(R.shape, np.nan)
    ok = np.isfinite(R).all(axis=(-2, -1))
    if np.any(ok):
        U, _, Vt = np.linalg.svd(R[ok])
        d = np.sign(np.linalg.det(U @ Vt))
        d[d == 0] = 1.0
        U[..., :, 2] *= d[..., None]
        out[ok] = U @ Vt
    return out


def rotation_error_deg(T_est: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """Geodesic angle (degrees, ``[0, 180]``) between the rotations of two poses.

    Both rotations are first projected onto SO(3) (:func:`nearest_rotation`):
    a rotation printed to 7 digits, as KITTI's poses are, is off by ~1e-7 in
    each entry, which pushed the trace above 3 and read small errors as 0.0.
    The angle is then ``atan2(|skew part|, (trace - 1) / 2)`` of
    ``R_est^T R_gt``, accurate near 0 and near 180 degrees alike, where the
    arccos of the trace alone loses half of its digits.

    Works on single poses or stacks ``(..., 4, 4)``; NaN in ``T_est`` gives NaN.
    """
    R_est = nearest_rotation(np.asarray(T_est, dtype=np.float64)[..., :3, :3])
    R_gt = nearest_rotation(np.asarray(T_gt, dtype=np.float64)[..., :3, :3])
    M = np.swapaxes(R_est, -1, -2) @ R_gt
    skew = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0],
                     M[..., 1, 0] - M[..., 0, 1]], axis=-1)
    sin = np.linalg.norm(skew, axis=-1) / 2.0
    cos = (np.trace(M, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.rad2deg(np.arctan2(sin, cos))


def translation_error_m(T_est: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """Euclidean distance between the translations of two poses (metres)."""
    t_est = np.asarray(T_est, dtype=np.float64)[..., :3, 3]
    t_gt = np.asarray(T_gt, dtype=np.float64)[..., :3, 3]
    return np.linalg.norm(t_est - t_gt, axis=-1)


def yaw_error_deg(T_est: np.ndarray, T_gt: np.ndarray) -> np.ndarray:
    """Absolute difference of headings (degrees, ``[0, 180]``), wrapped.

    The rotation error of a yaw-only estimate: roll and pitch of the ground
    truth (a few degrees on real roads) are not the method's to recover.
    """
    d = yaw_deg_of(T_est) - yaw_deg_of(T_gt)
    return np.abs((d + 180.0) % 360.0 - 180.0)


def quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` of a rotation matrix, ``qw >= 0``.

    Shepperd's method: pick the largest of the four squared components to
    divide by, so the result stays accurate near 180 degrees.
    """
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    tr = np.trace(R)
    diag = np.array([R[0, 0], R[1, 1], R[2, 2]])
    k = int(np.argmax([tr, *diag]))
    if k == 0:
        w = np.sqrt(max(0.0, 1.0 + tr)) / 2.0
        q = [(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w),
             (R[1, 0] - R[0, 1]) / (4 * w), w]
    else:
        i = k - 1
        j, m = (i + 1) % 3, (i + 2) % 3
        v = np.sqrt(max(0.0, 1.0 + R[i, i] - R[j, j] - R[m, m])) / 2.0
        q = [0.0, 0.0, 0.0, (R[m, j] - R[j, m]) / (4 * v)]
        q[i] = v
        q[j] = (R[j, i] + R[i, j]) / (4 * v)
        q[m] = (R[m, i] + R[i, m]) / (4 * v)
    q = np.asarray(q, dtype=np.float64)
    q /= np.linalg.norm(q)
    return -q if q[3] < 0 else q


# --------------------------------------------------------------------------- Kabsch


def _kabsch_batch(src: np.ndarray, dst: np.ndarray, w: np.ndarray | None) -> np.ndarray:
    """Rigid fits of a batch: ``src, dst (B, s, 3)``, weights ``(B, s)`` -> ``(B, 4, 4)``."""
    if w is None:
        w = np.ones(src.shape[:2])
    wsum = w.sum(axis=1, keepdims=True)
    wn = w / np.where(wsum > 0, wsum, 1.0)
    cs = np.einsum("bs,bsk->bk", wn, src)
    cd = np.einsum("bs,bsk->bk", wn, dst)
    H = np.einsum("bs,bsi,bsj->bij", wn, src - cs[:, None], dst - cd[:, None])
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, 1, 2)
    Ut = np.swapaxes(U, 1, 2)
    # reflection guard: force det(R) = +1
    d = np.sign(np.linalg.det(V @ Ut))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros((len(src), 3, 3))
    D[:, 0, 0] = 1.0
    D[:, 1, 1] = 1.0
    D[:, 2, 2] = d
    R = V @ D @ Ut
    T = np.zeros((len(src), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = cd - np.einsum("bij,bj->bi", R, cs)
    T[:, 3, 3] = 1.0
    return T


def kabsch(src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares rigid transform ``T`` (det +1) minimising ``sum w ||dst - T src||^2``.

    Parameters
    ----------
    src, dst : ``(n, 3)`` corresponding points, ``n >= 3`` (fewer cannot fix
        a rotation; collinear points give one of the equally good rotations).
    weights : optional ``(n,)`` non-negative weights.

    Returns
    -------
    ``(4, 4)`` float64 pose mapping ``src`` onto ``dst``.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"kabsch needs two (n, 3) arrays, got {src.shape} and {dst.shape}")
    if len(src) < 3:
        raise ValueError(f"kabsch needs at least 3 correspondences, got {len(src)}")
    w = None if weights is None else np.asarray(weights, dtype=np.float64)[None]
    return _kabsch_batch(src[None], dst[None], w)[0]


# --------------------------------------------------------------------------- robust fits


@dataclass(frozen=True)
class RansacResult:
    """Outcome of a robust rigid fit.

    Attributes
    ----------
    pose : ``(4, 4)`` refit on the inliers of the best hypothesis (identity when
        there were fewer than ``sample_size`` correspondences).
    inliers : ``(n,)`` bool, residual below the threshold under ``pose``.
    residuals : ``(n,)`` float64 ``||dst - pose src||``.
    success : at least ``min_inliers`` inliers.
    hypotheses : number of hypotheses evaluated.
    """

    pose: np.ndarray
    inliers: np.ndarray
    residuals: np.ndarray
    success: bool
    hypotheses: int

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def _residuals(T: np.ndarray, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``(B, n)`` residuals of a batch of poses ``(B, 4, 4)``."""
    moved = np.einsum("bij,nj->bni", T[:, :3, :3], src) + T[:, None, :3, 3]
    return np.linalg.norm(moved - dst[None], axis=2)


def _distinct_samples(rng: np.random.Generator, n: int, count: int, size: int) -> np.ndarray:
    """``(count, size)`` index samples without repeats within a row."""
    samples = rng.integers(0, n, size=(count, size))
    while True:
        srt = np.sort(samples, axis=1)
        bad = np.any(srt[:, 1:] == srt[:, :-1], axis=1)
        if not bad.any():
            return samples
        samples[bad] = rng.integers(0, n, size=(int(bad.sum()), size))


def _check_pairs(src, dst, sample_size: int) -> tuple[np.ndarray, np.ndarray]:
    src = np.asarray(src, dtype=np.float64).reshape(-1, 3)
    dst = np.asarray(dst, dtype=np.float64).reshape(-1, 3)
    if src.shape != dst.shape:
        raise ValueError(f"src and dst differ in shape: {src.shape} vs {dst.shape}")
    if sample_size < 3:
        raise ValueError(f"sample_size must be at least 3, got {sample_size}")
    return src, dst


def _fail(n: int) -> RansacResult:
    return RansacResult(np.eye(4), np.zeros(n, bool), np.full(n, np.inf), False, 0)


def _score_hypotheses(
    samples: np.ndarray, src: np.ndarray, dst: np.ndarray, threshold: float,
    min_inliers: int, confidence: float | None,
) -> tuple[np.ndarray | None, int]:
    """Evaluate sample rows in order; return the best hypothesis and how many ran.

    The best is the one with most inliers, ties broken by the smaller sum of
    inlier residuals, then by the earlier hypothesis. With ``confidence``,
    evaluation stops after the batch in which the standard adaptive bound
    ``log(1 - confidence) / log(1 - w^s)`` (``w`` = best inlier ratio) is met.
    """
    n, s = len(src), samples.shape[1]
    best_T, best_key, ran = None, (-1, 0.0), 0
    for a in range(0, len(samples), _BATCH):
        idx = samples[a: a + _BATCH]
        T = _kabsch_batch(src[idx], dst[idx], None)
        r = _residuals(T, src, dst)
        inl = r < threshold
        count = inl.sum(axis=1)
        cost = np.where(inl, r, 0.0).sum(axis=1)
        ran += len(idx)
        order = np.lexsort((np.arange(len(idx)), cost, -count))
        b = order[0]
        key = (int(count[b]), -float(cost[b]))
        if key > best_key:
            best_key, best_T = key, T[b]
        if confidence is not None and best_key[0] >= max(min_inliers, s):
            w = best_key[0] / n
            if w >= 1.0:
                break
            need = np.log(1.0 - confidence) / np.log(1.0 - w**s)
            if ran >= need:
                break
    return best_T, ran


def _refit(
    T: np.ndarray, src: np.ndarray, dst: np.ndarray, threshold: float, rounds: int = 3
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Refit on inliers until the inlier set stops changing (at most ``rounds``)."""
    r = _residuals(T[None], src, dst)[0]
    inl = r < threshold
    for _ in range(rounds):
        if inl.sum() < 3:
            break
        T_new = kabsch(src[inl], dst[inl])
        r_new = _residuals(T_new[None], src, dst)[0]
        inl_new = r_new < threshold
        if inl_new.sum() < inl.sum():
            break
        T, r, changed, inl = T_new, r_new, bool(np.any(inl_new != inl)), inl_new
        if not changed:
            break
    return T, inl, r


def ransac_rigid(
    src: np.ndarray, dst: np.ndarray, *, threshold: float, iterations: int,
    min_inliers: int, rng: np.random.Generator, sample_size: int = 3,
    confidence: float | None = None,
) -> RansacResult:
    """RANSAC rigid fit of correspondences ``src[k] <-> dst[k]`` (Fischler & Bolles 1981).

    Draws ``iterations`` minimal samples of ``sample_size`` distinct pairs,
    fits each with :func:`kabsch`, keeps the hypothesis with most inliers
    (residual ``< threshold``), then refits on its inliers.

    Parameters
    ----------
    threshold : inlier residual bound, in the units of the points (metres).
    iterations : maximum number of hypotheses.
    min_inliers : inliers needed for ``success``.
    rng : the only source of randomness; same state -> same result.
    confidence : optional early stop (e.g. 0.99); ``None`` runs every iteration.
    """
    src, dst = _check_pairs(src, dst, sample_size)
    n = len(src)
    if n < sample_size or iterations < 1:
        return _fail(n)
    samples = _distinct_samples(rng, n, iterations, sample_size)
    T, ran = _score_hypotheses(samples, src, dst, threshold, min_inliers, confidence)
    T, inl, r = _refit(T, src, dst, threshold)
    return RansacResult(T, inl, r, bool(inl.sum() >= min_inliers), ran)


def prosac_samples(
    n: int, iterations: int, sample_size: int, rng: np.random.Generator
) -> np.ndarray:
    """PROSAC sample sequence (Chum & Matas 2005) over quality-sorted indices ``0..n-1``.

    Hypothesis ``t`` draws from the top-``m`` correspondences, where ``m``
    grows from ``sample_size`` to ``n`` following the paper's growth function
    ``T'_m`` with ``T_N = iterations``: while ``t <= T'_m`` the sample is
    correspondence ``m - 1`` plus ``sample_size - 1`` random ones from the top
    ``m - 1``; afterwards all are drawn from the top ``m``. Once ``m = n`` it
    is plain RANSAC.
    """
    s = sample_size
    T_N = max(iterations, 1)
    # T_m: expected number of samples drawn only from the top-m (paper eq. 3)
    T_m = float(T_N)
    for i in range(s):
        T_m *= (s - i) / (n - i)
    Tp_m, m = 1, s  # T'_m and current subset size
    out = np.empty((iterations, s), dtype=np.int64)
    for t in range(1, iterations + 1):
        if t > Tp_m and m < n:
            T_next = T_m * (m + 1) / (m + 1 - s)
            Tp_m = Tp_m + int(np.ceil(T_next - T_m))
            T_m = T_next
            m += 1
        if t <= Tp_m and m > s:
            rest = rng.choice(m - 1, size=s - 1, replace=False)
            out[t - 1] = np.concatenate([rest, [m - 1]])
        else:
            out[t - 1] = rng.choice(m, size=s, replace=False)
    return out


def prosac_rigid(
    src: np.ndarray, dst: np.ndarray, order: np.ndarray, *, threshold: float,
    iterations: int, min_inliers: int, rng: np.random.Generator, sample_size: int = 3,
    confidence: float | None = None,
) -> RansacResult:
    """PROSAC rigid fit: like :func:`ransac_rigid`, sampling best pairs first.

    ``order`` lists correspondence indices by decreasing quality (e.g. by
    increasing descriptor distance); PROSAC tries hypotheses from the
    best-ranked pairs first and converges to RANSAC, so with good rankings the
    right pose is found in far fewer iterations (use ``confidence`` to stop).
    Residuals and inliers in the result are indexed like ``src``, not ``order``.
    """
    src, dst = _check_pairs(src, dst, sample_size)
    n = len(src)
    order = np.asarray(order, dtype=np.int64)
    if sorted(order.tolist()) != list(range(n)):
        raise ValueError("order must be a permutation of range(len(src))")
    if n < sample_size or iterations < 1:
        return _fail(n)
    samples = order[prosac_samples(n, iterations, sample_size, rng)]
    T, ran = _score_hypotheses(samples, src, dst, threshold, min_inliers, confidence)
    T, inl, r = _refit(T, src, dst, threshold)
    return RansacResult(T, inl, r, bool(inl.sum() >= min_inliers), ran)


# --------------------------------------------------------------------------- neighbours


def nearest_neighbours(a: np.ndarray, b: np.ndarray, k: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest rows of ``b`` for each row of ``a`` (Euclidean).

    Returns ``(dist, idx)`` of shape ``(n,)`` when ``k == 1`` and ``(n, k)``
    otherwise (the ``scipy.spatial.cKDTree.query`` convention), nearest first;
    missing neighbours (``k > len(b)``) are ``inf`` / ``-1``. Low-dimensional
    inputs use a k-d tree, high-dimensional ones (feature descriptors) exact
    brute force in blocks; ties go to the smaller index in brute force.
    """
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    b = np.atleast_2d(np.asarray(b, dtype=np.float64))
    if a.shape[1] != b.shape[1] and len(a) and len(b):
        raise ValueError(f"dimension mismatch: {a.shape} vs {b.shape}")
    n, m = len(a), len(b)
    dist = np.full((n, k), np.inf)
    idx = np.full((n, k), -1, dtype=np.int64)
    kk = min(k, m)
    if n and kk:
        if a.shape[1] <= _KDTREE_MAX_DIM:
            d, j = cKDTree(b).query(a, k=kk)
            dist[:, :kk] = d.reshape(n, kk)
            idx[:, :kk] = j.reshape(n, kk)
        else:
            bb = np.einsum("ij,ij->i", b, b)
            rows = max(1, (1 << 22) // max(m, 1))
            for s in range(0, n, rows):
                blk = a[s: s + rows]
                d2 = np.einsum("ij,ij->i", blk, blk)[:, None] + bb[None] - 2.0 * blk @ b.T
                np.maximum(d2, 0.0, out=d2)
                j = np.argsort(d2, axis=1, kind="stable")[:, :kk]
                dist[s: s + rows, :kk] = np.sqrt(np.take_along_axis(d2, j, axis=1))
                idx[s: s + rows, :kk] = j
    if k == 1:
        return dist[:, 0], idx[:, 0]
    return dist, idx


def mutual_nearest(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs ``(i, j)`` where ``b[j]`` is ``a[i]``'s nearest and vice versa.

    Returns ``(ia, ib, dist)``, ordered by ``ia``.
    """
    if len(a) == 0 or len(b) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0)
    d_ab, j_ab = nearest_neighbours(a, b)
    _, i_ba = nearest_neighbours(b, a)
    ia = np.flatnonzero((j_ab >= 0) & (i_ba[np.maximum(j_ab, 0)] == np.arange(len(j_ab))))
    return ia, j_ab[ia], d_ab[ia]
