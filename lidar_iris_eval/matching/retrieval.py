"""Retrieval + verification: protocols 1 and 2 for methods with a candidate search.

Two kinds of method use this module:

* **two-stage methods** (``Descriptor.two_stage``: GOSMatch, ESM, segment
  matchers) have no all-pairs distance. A database is prepared once
  (``prepare``), each query retrieves candidates (``retrieve``) and verifies
  them geometrically (``verify`` -> score, 4x4 pose, inliers);
* **global descriptors with a retrieval stage** (Scan Context's ring-key
  k-d tree) run protocol 1 on ``candidates=K`` the same way; their default
  ``verify`` is the full descriptor distance with a yaw-only pose.

Protocol 1 (:func:`two_stage_matches`): for each query ``i`` (``limits[i] >= 0``,
the standard rule is ``limits[i] = i - E``) the candidates are
``retrieve(db, i, limits[i] + 1, K)``, restricted to valid
indices, de-duplicated and sorted by frame index, then verified; the match is
the smallest score (ties: the smaller frame index), and its score is the
distance the PR curve thresholds. A query whose candidates are all rejected
(NaN/inf score) has no match.

Protocol 2 (:func:`two_stage_affinity`), see :data:`PROTOCOL2_RULE`.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor, Verification
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.matching.blocks import Affinity, BestMatches, query_limits
from lidar_iris_eval.matching.geometry import yaw_deg_of

#: how protocol 2 scores a two-stage method (written to metrics.json)
PROTOCOL2_RULE = (
    "two-stage: each frame's top-K retrieval candidates among all other frames are verified; "
    "a verified pair's distance is its verification score, every other pair (not retrieved, "
    "or rejected by verification) is never accepted; counts are all ordered pairs"
)


def check_retrieval(descriptor: Descriptor, k: int) -> None:
    """A LirisError when ``descriptor`` cannot retrieve or ``k`` is not positive."""
    if not descriptor.has_retrieval():
        raise LirisError(f"candidates {k}", f"{descriptor.name} has no retrieval stage")
    if k < 1:
        raise LirisError(f"candidates {k}", "must be at least 1")


def _candidates(descriptor, db, query: int, n_allowed: int, k: int) -> np.ndarray:
    """Valid, unique candidate frames of ``query`` in ``[0, n_allowed)``, sorted by index."""
    if n_allowed <= 0:
        return np.empty(0, np.int64)
    cand, _ = descriptor.retrieve(db, query, n_allowed, k)
    cand = np.asarray(cand, dtype=np.int64).reshape(-1)
    return np.unique(cand[(cand >= 0) & (cand < n_allowed)])


def _verify(descriptor, db, query: int, cand: np.ndarray) -> Verification:
    ver = descriptor.verify(db, query, cand)
    if len(ver.score) != len(cand):
        raise RuntimeError(f"{descriptor.name}.verify returned {len(ver.score)} scores for "
                           f"{len(cand)} candidates")
    return ver


def _clean_scores(score: np.ndarray) -> np.ndarray:
    score = np.asarray(score, dtype=np.float64)
    return np.where(np.isnan(score), np.inf, score)


def pose_yaw_deg(pose: np.ndarray) -> np.ndarray:
    """Yaw in the descriptor convention (``[0, 360)``) of poses candidate -> query.

    A pose ``Rz(a)`` means the candidate's points are the query's turned by
    ``-a``, so the descriptor yaw is ``-a``; NaN rotations give NaN.
    """
    return np.mod(-yaw_deg_of(pose), 360.0)


def _warm_up(descriptor, features) -> None:
    """Run prepare/retrieve/verify once on two frames, untimed, so compiling kernels
    (numba) is not reported as matching time."""
    if len(features) < 2:
        return
    small = features[:2]
    db = descriptor.prepare(small)
    cand = _candidates(descriptor, db, 1, 1, 1)
    if len(cand):
        descriptor.verify(db, 1, cand)


def two_stage_matches(
    descriptor: Descriptor,
    features,
    exclude,
    k: int,
    progress: Callable[[int], object] | None = None,
) -> BestMatches:
    """Protocol 1 best matches through retrieval + verification (module docstring).

    ``features`` is what extraction produced (stacked array or
    :class:`~lidar_iris_eval.descriptors.features.RaggedFeatures`); the
    database is ``descriptor.prepare(features)``, built once. ``exclude`` is
    E (query ``i`` retrieves among ``j <= i - E``) or the ``(N,)`` per-query
    limits of :func:`~lidar_iris_eval.matching.blocks.query_limits`.
    """
    if isinstance(exclude, (int, np.integer)) and exclude < 1:
        raise LirisError(f"exclude {exclude}", "exclusion window must be at least 1 frame")
    check_retrieval(descriptor, k)
    n = len(features)
    limits = query_limits(n, exclude)
    _warm_up(descriptor, features)
    start = time.perf_counter()
    db = descriptor.prepare(features)
    queries = np.flatnonzero(limits >= 0)
    match = np.full(len(queries), -1, dtype=np.int64)
    dist = np.full(len(queries), np.inf)
    yaw = np.full(len(queries), np.nan)
    pose = np.full((len(queries), 4, 4), np.nan)
    inliers = np.zeros(len(queries), dtype=np.int64)
    evaluations = 0
    for q, i in enumerate(queries):
        cand = _candidates(descriptor, db, int(i), int(limits[i] + 1), k)
        if len(cand):
            ver = _verify(descriptor, db, int(i), cand)
            score = _clean_scores(ver.score)
            evaluations += len(cand)
            best = int(np.argmin(score))  # cand is sorted: ties go to the smaller index
            if np.isfinite(score[best]):
                match[q], dist[q] = cand[best], score[best]
                pose[q] = ver.pose[best]
                inliers[q] = ver.inliers[best]
                yaw[q] = (ver.yaw_deg[best] if ver.yaw_deg is not None
                          else pose_yaw_deg(ver.pose[best]))
        if progress is not None:
            progress(1)
    seconds = time.perf_counter() - start
    source = f"two-stage:{k}" if descriptor.two_stage else f"candidates:{k}"
    return BestMatches(queries, match, dist, yaw, seconds, evaluations, source, pose,
                       inliers if descriptor.two_stage else None)


def two_stage_affinity(
    descriptor: Descriptor,
    features,
    k: int,
    progress: Callable[[int], object] | None = None,
) -> Affinity:
    """Protocol 2 affinity of a two-stage method under :data:`PROTOCOL2_RULE`.

    Returns an ``(N, N)`` float32 matrix holding the verification score of
    each frame's verified top-``k`` candidates and NaN elsewhere (NaN is
    never accepted by the PR sweep). ``n_evaluations`` counts verifications.
    """
    check_retrieval(descriptor, k)
    n = len(features)
    _warm_up(descriptor, features)
    start = time.perf_counter()
    db = descriptor.prepare(features)
    matrix = np.full((n, n), np.nan, dtype=np.float32)
    evaluations = 0
    for i in range(n):
        # ask for one more: the frame itself is usually its own best candidate
        ranked, _ = descriptor.retrieve(db, i, n, k + 1)
        ranked = np.asarray(ranked, dtype=np.int64).reshape(-1)
        ranked = ranked[(ranked >= 0) & (ranked < n) & (ranked != i)]
        _, first = np.unique(ranked, return_index=True)
        cand = np.sort(ranked[np.sort(first)][:k])  # best k in retrieval order, then by index
        if len(cand):
            score = _clean_scores(_verify(descriptor, db, i, cand).score)
            evaluations += len(cand)
            ok = np.isfinite(score)
            matrix[i, cand[ok]] = score[ok]
        if progress is not None:
            progress(1)
    return Affinity(matrix, time.perf_counter() - start, evaluations, False)
