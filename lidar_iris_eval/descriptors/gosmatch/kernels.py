"""Compiled GOSMatch verification (numba): all candidates of one query in one call.

The NumPy path (:func:`.verification.verify_pair` around
:func:`lidar_iris_eval.matching.geometry.ransac_rigid`) costs about 2-5 ms per
pair, mostly in the overhead of small batched NumPy calls; protocol 1 on
KITTI 00 verifies ~45,000 pairs. This module does the same steps in one
compiled loop:

* same-class nearest vertex descriptor (squared L2, ties to the lower index);
* RANSAC with hypotheses ranked exactly like ``ransac_rigid`` (most inliers,
  then smallest sum of inlier residuals, then the earliest), followed by the
  same refit loop (at most 3 rounds, stop when the inlier set shrinks or stops
  changing) and the same Kabsch fit with a det +1 guard;
* the named score.

Given the same minimal samples, :func:`ransac_from_samples` returns the pose,
inliers and residuals of ``geometry``'s ``_score_hypotheses`` + ``_refit``
(tested). Samples come from a small counter-based generator (SplitMix64)
seeded by ``(seed, query, candidate)``, so a pair's result does not depend on
which other pairs ran before it or in which process.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)
_TWO_POW_M53 = 1.0 / 9007199254740992.0

#: score codes of the kernel
SCORE_CODES = {"clipped-mean": 0, "inlier-mean": 1}


@nb.njit(cache=True, nogil=True)
def _mix(z):
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


@nb.njit(cache=True, nogil=True)
def pair_state(seed: int, query: int, candidate: int):
    """Initial generator state of one (query, candidate) pair."""
    s = _mix(np.uint64(seed) + _GOLDEN)
    s = _mix(s ^ (np.uint64(query) + _GOLDEN))
    return _mix(s ^ (np.uint64(candidate) + _GOLDEN))


@nb.njit(cache=True, nogil=True)
def _below(state, n: int):
    """Next state and a uniform integer in ``[0, n)`` (53-bit float, floor)."""
    state = np.uint64(state) + _GOLDEN
    z = _mix(state)
    u = float(z >> np.uint64(11)) * _TWO_POW_M53
    k = int(u * n)
    return state, min(k, n - 1)


@nb.njit(cache=True, nogil=True)
def draw_samples(seed: int, query: int, candidate: int, n: int, iterations: int) -> np.ndarray:
    """``(iterations, 3)`` triples of distinct indices in ``[0, n)`` for one pair, uniformly."""
    out = np.empty((iterations, 3), dtype=np.int64)
    state = pair_state(seed, query, candidate)
    for it in range(iterations):
        state, a = _below(state, n)
        state, b = _below(state, n - 1)
        if b >= a:
            b += 1
        state, c = _below(state, n - 2)
        lo, hi = min(a, b), max(a, b)
        if c >= lo:
            c += 1
        if c >= hi:
            c += 1
        out[it, 0], out[it, 1], out[it, 2] = a, b, c
    return out


@nb.njit(cache=True, nogil=True)
def _sym_eig3(A: np.ndarray, V: np.ndarray) -> None:
    """Eigen-decompose the symmetric 3x3 ``A`` in place: ``V`` gets the eigenvectors
    (columns), ``diag(A)`` the eigenvalues, both unsorted.

    Cyclic Jacobi rotations until the off-diagonal part is negligible: exact to
    rounding, and far cheaper than a LAPACK call from compiled code.
    """
    V[:, :] = 0.0
    V[0, 0] = V[1, 1] = V[2, 2] = 1.0
    for _ in range(32):
        off = A[0, 1] * A[0, 1] + A[0, 2] * A[0, 2] + A[1, 2] * A[1, 2]
        scale = A[0, 0] * A[0, 0] + A[1, 1] * A[1, 1] + A[2, 2] * A[2, 2]
        if off <= 1e-30 * scale or off == 0.0:
            break
        for r in range(3):
            p = 0 if r < 2 else 1
            q = 1 if r == 0 else 2
            apq = A[p, q]
            if apq == 0.0:
                continue
            theta = (A[q, q] - A[p, p]) / (2.0 * apq)
            t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + np.sqrt(theta * theta + 1.0))
            c = 1.0 / np.sqrt(t * t + 1.0)
            sn = t * c
            for k in range(3):
                akp, akq = A[k, p], A[k, q]
                A[k, p] = c * akp - sn * akq
                A[k, q] = sn * akp + c * akq
            for k in range(3):
                apk, aqk = A[p, k], A[q, k]
                A[p, k] = c * apk - sn * aqk
                A[q, k] = sn * apk + c * aqk
            for k in range(3):
                vkp, vkq = V[k, p], V[k, q]
                V[k, p] = c * vkp - sn * vkq
                V[k, q] = sn * vkp + c * vkq


@nb.njit(cache=True, nogil=True)
def _kabsch(src: np.ndarray, dst: np.ndarray, use: np.ndarray, out: np.ndarray) -> None:
    """Least-squares rigid fit of ``src[use] -> dst[use]`` into ``out`` (4x4), det +1.

    With ``H = sum (s - cs)(d - cd)^T = U S V^T`` Kabsch's rotation is
    ``V diag(1, 1, sign det(V U^T)) U^T``, which equals
    ``v1 u1^T + v2 u2^T + (v1 x v2)(u1 x u2)^T`` built from the two leading
    singular pairs (right-handed completions carry the determinant sign). The
    ``v`` are eigenvectors of ``H^T H``, ``u_i = H v_i / |H v_i|``; only the
    third singular pair, undefined for three points, is never needed.
    """
    m = 0
    cs0 = cs1 = cs2 = cd0 = cd1 = cd2 = 0.0
    for k in range(len(use)):
        if use[k]:
            m += 1
            cs0 += src[k, 0]
            cs1 += src[k, 1]
            cs2 += src[k, 2]
            cd0 += dst[k, 0]
            cd1 += dst[k, 1]
            cd2 += dst[k, 2]
    cs = np.array([cs0 / m, cs1 / m, cs2 / m])
    cd = np.array([cd0 / m, cd1 / m, cd2 / m])
    H = np.zeros((3, 3))
    for k in range(len(use)):
        if use[k]:
            for a in range(3):
                sa = src[k, a] - cs[a]
                for b in range(3):
                    H[a, b] += sa * (dst[k, b] - cd[b])
    A = np.empty((3, 3))
    for a in range(3):
        for b in range(3):
            A[a, b] = H[0, a] * H[0, b] + H[1, a] * H[1, b] + H[2, a] * H[2, b]
    V = np.empty((3, 3))
    _sym_eig3(A, V)
    # the two largest eigenvalues' vectors
    i1 = 0
    for a in range(1, 3):
        if A[a, a] > A[i1, i1]:
            i1 = a
    i2 = -1
    for a in range(3):
        if a != i1 and (i2 < 0 or A[a, a] > A[i2, i2]):
            i2 = a
    v1 = V[:, i1].copy()
    v2 = V[:, i2].copy()
    u1 = H @ v1
    n1 = np.sqrt(u1 @ u1)
    u1 = u1 / n1 if n1 > 0 else np.array([1.0, 0.0, 0.0])
    u2 = H @ v2
    u2 = u2 - (u2 @ u1) * u1
    n2 = np.sqrt(u2 @ u2)
    if n2 > 1e-12 * max(n1, 1e-300):
        u2 = u2 / n2
    else:  # collinear points: any rotation about the line fits; pick one
        u2 = _cross(u1, np.array([1.0, 0.0, 0.0]) if abs(u1[0]) < 0.9
                    else np.array([0.0, 1.0, 0.0]))
        u2 = u2 / np.sqrt(u2 @ u2)
    v3 = _cross(v1, v2)
    u3 = _cross(u1, u2)
    out[:, :] = 0.0
    for a in range(3):
        for b in range(3):
            out[a, b] = v1[a] * u1[b] + v2[a] * u2[b] + v3[a] * u3[b]
    for a in range(3):
        out[a, 3] = cd[a] - (out[a, 0] * cs[0] + out[a, 1] * cs[1] + out[a, 2] * cs[2])
    out[3, 3] = 1.0


@nb.njit(cache=True, nogil=True)
def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


@nb.njit(cache=True, nogil=True)
def _residuals(T: np.ndarray, src: np.ndarray, dst: np.ndarray, r: np.ndarray) -> None:
    for k in range(len(src)):
        acc = 0.0
        for a in range(3):
            v = T[a, 0] * src[k, 0] + T[a, 1] * src[k, 1] + T[a, 2] * src[k, 2] + T[a, 3]
            v -= dst[k, a]
            acc += v * v
        r[k] = np.sqrt(acc)


@nb.njit(cache=True, nogil=True)
def ransac_from_samples(src: np.ndarray, dst: np.ndarray, samples: np.ndarray, threshold: float):
    """Best hypothesis of ``samples`` and its refit: ``(pose, inliers, residuals)``."""
    n = len(src)
    T = np.empty((4, 4))
    best = np.eye(4)
    best_count, best_cost = -1, 0.0
    use = np.zeros(n, dtype=np.bool_)
    r = np.empty(n)
    for it in range(len(samples)):
        use[:] = False
        for s in range(samples.shape[1]):
            use[samples[it, s]] = True
        # a sample's three points, in sample order, as geometry's batch fit sees them
        _kabsch(src, dst, use, T)
        _residuals(T, src, dst, r)
        count, cost = 0, 0.0
        for k in range(n):
            if r[k] < threshold:
                count += 1
                cost += r[k]
        if count > best_count or (count == best_count and cost < best_cost):
            best_count, best_cost = count, cost
            best[:, :] = T
    # refit on inliers until the set shrinks or stops changing (at most 3 rounds)
    _residuals(best, src, dst, r)
    inl = r < threshold
    r_new = np.empty(n)
    for _ in range(3):
        if inl.sum() < 3:
            break
        _kabsch(src, dst, inl, T)
        _residuals(T, src, dst, r_new)
        inl_new = r_new < threshold
        if inl_new.sum() < inl.sum():
            break
        changed = False
        for k in range(n):
            if inl_new[k] != inl[k]:
                changed = True
        best[:, :] = T
        r[:] = r_new
        inl = inl_new
        if not changed:
            break
    return best, inl, r


@nb.njit(cache=True, nogil=True)
def _class_nearest(qv, qc, cv, cc, iq, ic) -> int:
    """Same-class nearest candidate vertex of each query vertex; returns the pair count."""
    m = 0
    dim = qv.shape[1]
    for a in range(len(qv)):
        best, best_j = np.inf, -1
        for j in range(len(cv)):
            if cc[j] != qc[a]:
                continue
            acc = 0.0
            for t in range(dim):
                diff = qv[a, t] - cv[j, t]
                acc += diff * diff
            if acc < best:
                best, best_j = acc, j
        if best_j >= 0:
            iq[m] = a
            ic[m] = best_j
            m += 1
    return m


@nb.njit(cache=True, nogil=True)
def _verify_pair(
    query: int, c: int, offsets: np.ndarray, centroids: np.ndarray, classes: np.ndarray,
    vertex: np.ndarray, iterations: int, threshold: float, min_inliers: int, score_code: int,
    seed: int, pose_out: np.ndarray,
):
    """Score and inlier count of one pair; the pose is written to ``pose_out``."""
    qa, qb = offsets[query], offsets[query + 1]
    ca, cb = offsets[c], offsets[c + 1]
    iq = np.empty(qb - qa, dtype=np.int64)
    ic = np.empty(qb - qa, dtype=np.int64)
    need = max(3, min_inliers)
    m = _class_nearest(vertex[qa:qb], classes[qa:qb], vertex[ca:cb], classes[ca:cb], iq, ic)
    if m < need:
        return np.inf, 0
    src = np.empty((m, 3))
    dst = np.empty((m, 3))
    for p in range(m):
        src[p] = centroids[ca + ic[p]]
        dst[p] = centroids[qa + iq[p]]
    samples = draw_samples(seed, query, c, m, iterations)
    T, inl, r = ransac_from_samples(src, dst, samples, threshold)
    n_in = int(inl.sum())
    if n_in < need:
        return np.inf, n_in
    total = 0.0
    if score_code == 0:
        for p in range(m):
            total += min(r[p], threshold)
        score = total / m
    else:
        for p in range(m):
            if inl[p]:
                total += r[p]
        score = total / n_in
    pose_out[:, :] = T
    return score, n_in


@nb.njit(cache=True, nogil=True)
def verify_query(
    query: int, candidates: np.ndarray, offsets: np.ndarray, centroids: np.ndarray,
    classes: np.ndarray, vertex: np.ndarray, iterations: int, threshold: float,
    min_inliers: int, score_code: int, seed: int,
):
    """Score, pose and inlier count of every candidate of one query.

    ``offsets`` (N + 1) slice the flat ``centroids``/``classes``/``vertex`` rows
    of each frame. Rejected candidates get ``inf`` and a NaN pose. Each pair
    draws from its own sample stream, so the result does not depend on the
    order or grouping of candidates. Serial on purpose: threads over ~10
    candidates of ~0.2 ms each cost more than they gain on a busy machine
    (measured: 3.7x the CPU time with 2 numba threads at load average 9).
    """
    k = len(candidates)
    scores = np.full(k, np.inf)
    poses = np.full((k, 4, 4), np.nan)
    inliers = np.zeros(k, dtype=np.int64)
    for t in range(k):
        scores[t], inliers[t] = _verify_pair(
            query, candidates[t], offsets, centroids, classes, vertex, iterations, threshold,
            min_inliers, score_code, seed, poses[t],
        )
    return scores, poses, inliers
