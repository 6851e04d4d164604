"""SegMap's target map and ESM's verification on local maps.

**Target map** (ethz-asl/segmap ``SegMatch::filterDuplicateSegmentsOfTargetMap``):
the segments of each frame's local map enter the target in frame order; a new
segment whose centroid is within ``dedup`` (2 m) of a target segment either
replaces it (the target segment was seen recently: fewer than ``window``
frames earlier, SegMap's 60 s) or is dropped (an old segment: a revisit keeps
the first view). Which recent view stays (``keep``):

* ``latest``: every newer view replaces (SegMap's rule as written);
* ``largest``: a newer view replaces only when it holds at least as many
  voxels. SegMap's local map is the 50 m cylinder alone, so a segment's
  voxels only grow while it is in range and its latest view is also its
  largest. Our local map also drops scans older than the window W = E, so a
  segment's latest view is the one built from the scans that saw it leave,
  far behind (median 40-60 m on ``small-mixed``): ``largest`` keeps what
  SegMap's rule keeps in SegMap's own setting (docs/esm.md, "Which view the
  target keeps").

:func:`target_lifetimes` turns that process into, per segment, the range of
database sizes it is alive for, so the target for "the frames ``[0, n)``" is
one mask and does not depend on the order queries ask.

**Verification** (:func:`localise`): per query segment its ``K = min(knn, N - 1)``
nearest target segments (squared L2 in the 16-d embedding); the
correspondences are ordered by the product of their qualities (PROSAC's
order). Two correspondences are *consistent* when the distance between their
query centroids and between their target centroids differ by at most
``threshold`` (SegMap's centroid consistency, 0.6 m). Hypotheses are seeded in
PROSAC order: from each of the first ``iterations`` correspondences a
consistent set is grown greedily (in the same order; a set never uses a query
or a target segment twice); a set of at least ``min_consistent`` (SegMap's 6)
gives a rigid fit (Kabsch) whose inliers (residual <= threshold, one per query
segment) are counted; the fit with the most inliers wins (ties: the earlier
seed). Consistency is evaluated only where the sets read it
(:func:`_consistent_sets`: the seeds' rows, and a member's row over the
correspondences still allowed), never as the whole ``n x n`` matrix, with the
same float32 distances and comparisons, so the decisions are the dense
matrix's (tests/test_esm_localise.py). The matched frame (``frame_rule``):

* ``estimate`` (default): the database frame whose odometry position is nearest
  the query's position the fit estimates in the world; rejected when that
  frame is farther than ``max_offset`` (4 m) from it. A local map reaches
  50 m, so a query also localises correctly against the target segments of
  the frames just before its window (22 m back on ``small-mixed``): that is
  a correct localisation but not a revisit, and the fit itself says so;
* ``segments`` (SegMap's ``findTimeOfClosestPose``): the database frame whose
  position is nearest, in total distance, to the inlier target centroids;
  measured in docs/esm.md (it labels most of those localisations as
  matches 10-20 m away).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numba
import numpy as np
from scipy.spatial import cKDTree

from lidar_iris_eval.matching.geometry import kabsch

#: which recent view of a segment the target map keeps (module docstring)
TARGET_VIEWS = ("latest", "largest")
#: how a seed's consistent set grows (:func:`_consistent_sets`)
GROW_RULES = ("order", "degree")


def target_lifetimes(world: np.ndarray, frame_of: np.ndarray, n_frames: int, dedup: float,
                     recent: int, sizes: np.ndarray | None = None,
                     keep: str = "latest") -> np.ndarray:
    """Per segment the last database size ``n`` it is in the target for (``-1``: never).

    Segment ``s`` of frame ``f`` is in the target of the frames ``[0, n)`` when
    ``f < n <= alive_until[s]``. Frame ``f``'s segments are added when the
    database grows to ``f + 1`` frames; a target segment replaced by frame
    ``k`` is alive until ``n = k``. ``keep`` is ``"latest"`` or ``"largest"``
    (module docstring); ``"largest"`` needs ``sizes``, the voxels per segment.
    """
    if keep not in TARGET_VIEWS:
        raise ValueError(f"keep must be one of {TARGET_VIEWS}, got {keep!r}")
    if keep == "largest" and (sizes is None or len(sizes) != len(frame_of)):
        raise ValueError("keep='largest' needs one size per segment")
    inf = np.iinfo(np.int64).max
    alive_until = np.full(len(frame_of), inf, np.int64)
    starts = np.searchsorted(frame_of, np.arange(n_frames + 1))
    alive: list[int] = []
    for f in range(n_frames):
        new = np.arange(starts[f], starts[f + 1])
        if len(new) == 0:
            continue
        if alive:
            alive_arr = np.asarray(alive, np.int64)
            tree = cKDTree(world[alive_arr])
            near = tree.query_ball_point(world[new], dedup)
            drop_old: set[int] = set()
            keep_new = np.ones(len(new), bool)
            for a, hits in enumerate(near):
                for h in sorted(hits):
                    old = int(alive_arr[h])
                    if frame_of[old] > f - recent:
                        if keep == "largest" and sizes[new[a]] < sizes[old]:
                            keep_new[a] = False  # a smaller recent view: the larger stays
                        else:
                            drop_old.add(old)  # seen recently: the newer view replaces it
                    else:
                        keep_new[a] = False  # a revisit: the old view stays
            for old in drop_old:
                alive_until[old] = f
            alive = [s for s in alive if s not in drop_old]
            alive_until[new[~keep_new]] = -1
            alive.extend(int(s) for s in new[keep_new])
        else:
            alive.extend(int(s) for s in new)
    return alive_until


@dataclass(frozen=True)
class Localisation:
    """The outcome of one query against a target map."""

    frame: int  # matched database frame, -1 when rejected
    world_to_query: np.ndarray  # (4, 4), NaN when rejected
    inliers: int
    residual: float  # mean inlier residual (m), NaN when rejected
    hypotheses: int
    #: CPU time of (matching: k-NN + consistency, as the consistent sets grow; pose
    #: estimation: the rigid fits and the frame)
    seconds: tuple = (0.0, 0.0)


def _rejected(hyp: int = 0, inliers: int = 0, seconds=(0.0, 0.0)) -> Localisation:
    return Localisation(-1, np.full((4, 4), np.nan), inliers, float("nan"), hyp, seconds)


def localise(q_emb, q_qual, q_cent, t_emb, t_qual, t_world, t_ids, positions, *, knn: int,
             threshold: float, min_consistent: int, iterations: int,
             frame_rule: str = "estimate", max_offset: float = 4.0,
             grow: str = "order") -> Localisation:
    """Match query segments against target segments (module docstring).

    ``q_cent`` are query centroids in the query's LiDAR frame, ``t_world``
    target centroids in the world frame, ``t_ids`` their global row ids (for
    tie-breaking), ``positions`` the ``(n, 3)`` odometry positions of the
    allowed database frames.
    """
    nq, nt = len(q_emb), len(t_emb)
    if nq == 0 or nt < 2:
        return _rejected()
    t0 = time.thread_time()
    k = min(knn, nt - 1)
    qe, te = q_emb.astype(np.float64), t_emb.astype(np.float64)
    d2 = (qe**2).sum(1)[:, None] + (te**2).sum(1)[None, :] - 2.0 * qe @ te.T
    nn = np.argpartition(d2, k - 1, axis=1)[:, :k]
    qa = np.repeat(np.arange(nq), k)
    tb = nn.ravel()
    prod = q_qual[qa] * t_qual[tb]
    dist = d2[qa, tb]
    order = np.lexsort((t_ids[tb], qa, dist, -prod))
    qa, tb = qa[order], tb[order]
    src, dst = t_world[tb], q_cent[qa]
    n = len(qa)
    tried = max(0, min(iterations, n))
    sets = _consistent_sets(qa, tb, t_world, q_cent, threshold, min_consistent, tried, grow)
    t1 = time.thread_time()
    best = None
    for seed, m in sets:
        T = kabsch(src[m], dst[m])
        resid = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1)
        inl = _one_per_query(resid, qa, threshold)
        if len(inl) >= 3:
            T = kabsch(src[inl], dst[inl])
            resid = np.linalg.norm(src @ T[:3, :3].T + T[:3, 3] - dst, axis=1)
            inl = _one_per_query(resid, qa, threshold)
        score = (len(inl), -seed)
        if best is None or score > best[0]:
            best = (score, T, inl, resid)
    seconds = (t1 - t0, time.thread_time() - t1)
    if best is None or best[0][0] < min_consistent:
        return _rejected(tried, 0 if best is None else best[0][0], seconds)
    _, T, inl, resid = best
    if frame_rule == "segments":  # SegMap: least total distance to the matched targets
        total = np.linalg.norm(positions[:, None, :] - src[inl][None], axis=2).sum(1)
        frame = int(np.argmin(total))  # ties: the earlier frame
    else:  # the frame nearest the query's estimated position in the world
        where = np.linalg.inv(T)[:3, 3]
        offset = np.linalg.norm(positions - where, axis=1)
        frame = int(np.argmin(offset))
        if offset[frame] > max_offset:
            return _rejected(tried, len(inl), seconds)
    return Localisation(frame, T, len(inl), float(resid[inl].mean()), tried, seconds)


#: seeds whose consistency rows are formed together (bounds memory to ~_SEED_BLOCK * n)
_SEED_BLOCK = 64


def _centroid_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances between centroids ``a`` and ``b`` (broadcast), float32.

    The float64 difference is rounded to float32, squared, summed as
    ``(x + y) + z`` and square-rooted: the operations, in the same order, of
    ``np.linalg.norm(diff.astype(np.float32), axis=-1)`` that the dense
    ``(n, n)`` consistency matrix used, written out so that the result does
    not depend on how NumPy happens to order a reduction for a given shape
    (tests/test_esm_localise.py and ``bench_esm_localmaps.py time`` check it
    against the dense matrix).
    """
    d = (a - b).astype(np.float32)
    s = d * d
    return np.sqrt((s[..., 0] + s[..., 1]) + s[..., 2])


def _consistent_sets(qa: np.ndarray, tb: np.ndarray, t_world: np.ndarray, q_cent: np.ndarray,
                     threshold: float, min_consistent: int, seeds: int,
                     grow: str = "order") -> list:
    """The greedy consistent set grown from each of the first ``seeds`` correspondences.

    ``grow`` (:data:`GROW_RULES`) picks the next member among those still allowed:
    ``order`` the first in PROSAC order (:func:`_grow`), ``degree`` the one
    consistent with most of the others still allowed (:func:`_grow_degree`).

    Returns ``(seed, members)`` for the seeds whose set reaches
    ``min_consistent``, members in the order they joined (the seed first).
    The result is the one of a dense ``(n, n)`` consistency matrix ``ok``
    (``|d_target - d_query| <= threshold``, never the same query or target
    segment twice) with ``allowed = ok[seed]; while any: c = first allowed;
    allowed &= ok[c]``; but only the rows that loop reads are formed, and a
    member's row only over the correspondences still allowed: about
    ``seeds * n`` pairs instead of ``n**2`` (n = 3,100 on ``urban-dense``).
    Query-side distances depend only on the two query segments and
    target-side ones only on the two target segments, so they are computed
    once per pair of segments (``dq``, ``dt``) and gathered; every distance
    is the same float32 number the dense matrix held (:func:`_centroid_distances`),
    compared the same way, so every decision is the same.
    """
    src = t_world[tb]
    dq = _centroid_distances(q_cent[:, None], q_cent[None])  # (nq, nq)
    targets, t_of = np.unique(tb, return_inverse=True)
    t_cent = t_world[targets]
    limit = _comparison_limit(threshold)
    qa, tb = np.ascontiguousarray(qa, np.int64), np.ascontiguousarray(tb, np.int64)
    src = np.ascontiguousarray(src, np.float64)
    out = []
    for lo in range(0, seeds, _SEED_BLOCK):
        block = np.arange(lo, min(lo + _SEED_BLOCK, seeds))
        rows_of, inv = np.unique(t_of[block], return_inverse=True)
        dt = _centroid_distances(t_cent[rows_of][:, None], t_cent[None])  # (seed targets, targets)
        ok = np.abs(dt[inv][:, t_of] - dq[qa[block]][:, qa]) <= threshold
        ok &= qa[block, None] != qa[None, :]
        ok &= tb[block, None] != tb[None, :]
        for i, seed in enumerate(block.tolist()):
            allowed = np.flatnonzero(ok[i])
            if len(allowed) + 1 < min_consistent:
                continue
            if grow == "degree":
                members = _grow_degree(seed, allowed, src, dq, qa, tb, limit)
            else:
                members = _grow(seed, allowed, src, dq, qa, tb, limit)
            if len(members) >= min_consistent:
                out.append((seed, members))
    return out


@numba.njit(cache=True, inline="always")
def _agree(c: int, x: int, src: np.ndarray, dq: np.ndarray, qa: np.ndarray, tb: np.ndarray,
           limit: float) -> bool:  # pragma: no cover - compiled
    """Correspondences ``c`` and ``x`` are consistent (compiled, inlined into the growths).

    Never the same query or target segment; the target-side distance in
    :func:`_centroid_distances`' float32 arithmetic written per element (the float64
    difference rounded to float32, squares summed ``(x + y) + z``, a float32 square
    root) against the query-side ``dq``, compared with ``limit``, the threshold in the
    type NumPy compares a float32 array with (:func:`_comparison_limit`), so every
    decision is the vectorised one's.
    """
    if qa[x] == qa[c] or tb[x] == tb[c]:
        return False
    d0 = np.float32(src[c, 0] - src[x, 0])
    d1 = np.float32(src[c, 1] - src[x, 1])
    d2 = np.float32(src[c, 2] - src[x, 2])
    dist = np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)
    return np.float64(abs(dist - dq[qa[c], qa[x]])) <= limit


@numba.njit(cache=True)
def _grow(seed: int, allowed: np.ndarray, src: np.ndarray, dq: np.ndarray, qa: np.ndarray,
          tb: np.ndarray, limit: float) -> np.ndarray:  # pragma: no cover - compiled
    """One seed's greedy set (``_consistent_sets``' inner loop, compiled).

    Takes the first allowed correspondence ``c`` and keeps of the rest those
    consistent with it (:func:`_agree`), until none is left.
    """
    members = np.empty(len(allowed) + 1, np.int64)
    members[0] = seed
    m = 1
    rest = allowed.copy()
    n = len(rest)
    while n:
        c = rest[0]
        members[m] = c
        m += 1
        w = 0
        for r in range(1, n):
            x = rest[r]
            if _agree(c, x, src, dq, qa, tb, limit):
                rest[w] = x
                w += 1
        n = w
    return members[:m]


@numba.njit(cache=True)
def _grow_degree(seed: int, allowed: np.ndarray, src: np.ndarray, dq: np.ndarray,
                 qa: np.ndarray, tb: np.ndarray, limit: float) -> np.ndarray:  # pragma: no cover
    """One seed's greedy set, most-consistent candidate first (compiled).

    The consistency among the ``allowed`` correspondences (those consistent
    with the seed) is formed once (:func:`_agree`);
    then, while any is left, the candidate consistent with most of the others
    still left joins (ties: the earlier in PROSAC order) and the rest is cut to
    its consistent ones. The classic greedy approximation of a maximum clique
    (SegMap's incremental recogniser searches maximum cliques of this graph):
    a wrong correspondence that happens to come early in the quality order is
    consistent with few others and no longer blocks the true ones.
    """
    n = len(allowed)
    ok = np.zeros((n, n), np.bool_)
    for a in range(n):
        ca = allowed[a]
        for b in range(a + 1, n):
            if _agree(ca, allowed[b], src, dq, qa, tb, limit):
                ok[a, b] = True
                ok[b, a] = True
    alive = np.ones(n, np.bool_)
    degree = np.zeros(n, np.int64)
    for a in range(n):
        for b in range(n):
            if ok[a, b]:
                degree[a] += 1
    members = np.empty(n + 1, np.int64)
    members[0] = seed
    m = 1
    left = n
    while left:
        best = -1
        for a in range(n):
            if alive[a] and (best < 0 or degree[a] > degree[best]):
                best = a
        members[m] = allowed[best]
        m += 1
        alive[best] = False
        left -= 1
        for r in range(n):  # cut the rest to best's consistent ones
            if alive[r] and not ok[best, r]:
                alive[r] = False
                left -= 1
                for b in range(n):
                    if ok[r, b]:
                        degree[b] -= 1
    return members[:m]


def _comparison_limit(threshold: float) -> float:
    """``threshold`` as NumPy compares it with a float32 array: a Python float is cast to
    float32 (NEP 50), a NumPy float64 is not; returned as the float64 holding that value."""
    return float(np.result_type(np.float32(0), threshold).type(threshold))


def _one_per_query(resid: np.ndarray, qa: np.ndarray, threshold: float) -> np.ndarray:
    """Inlier correspondences, the smallest residual per query segment (ties: earlier)."""
    idx = np.nonzero(resid <= threshold)[0]
    if len(idx) == 0:
        return idx
    idx = idx[np.lexsort((idx, resid[idx], qa[idx]))]
    first = np.concatenate([[True], qa[idx][1:] != qa[idx][:-1]])
    return np.sort(idx[first])
