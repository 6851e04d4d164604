"""Geometric verification of a GOSMatch candidate: vertex matching, RANSAC, score.

The authors never released this stage (their issue #1); the paper says: match
vertices by their descriptors, estimate a 6-DoF transform with RANSAC and SVD,
and accept the loop when the loss is small. Here:

1. **Correspondences**: every query vertex is paired with the candidate vertex
   *of the same class* whose vertex descriptor is nearest (Euclidean; ties to
   the lower index). Query vertices of a class the candidate lacks get none.
2. **Pose**: :func:`lidar_iris_eval.matching.geometry.ransac_rigid`: 3-point
   Kabsch hypotheses, the one with most inliers (residual ``< threshold``),
   refit by SVD on its inliers. ``T`` maps candidate centroids onto query
   centroids (candidate LiDAR frame -> query LiDAR frame).
3. **Score** (smaller = more similar; ``inf`` = rejected: fewer than
   ``min_inliers`` inliers or fewer than 3 correspondences):

   ``clipped-mean``
       mean over *all* correspondences of ``min(residual, threshold)``: an
       outlier costs the full threshold, so a pose explaining 4 of 20 objects
       scores worse than one explaining 15. Stable across RANSAC seeds.
   ``inlier-mean``
       mean residual of the inliers only (the loss the paper describes). A
       lucky 4-inlier fit on an unrelated scan can score near 0, so its
       ranking of loops depends on the seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.matching.geometry import ransac_rigid

SCORES = ("clipped-mean", "inlier-mean")


@dataclass(frozen=True)
class VerifySettings:
    """The verification parameters (see the module docstring)."""

    iterations: int = 100
    threshold: float = 1.0
    min_inliers: int = 4
    score: str = "clipped-mean"


@dataclass(frozen=True)
class PairResult:
    """Verification of one (query, candidate) pair."""

    score: float
    pose: np.ndarray
    inliers: int
    correspondences: int


def class_nearest(
    q_vertex: np.ndarray, q_classes: np.ndarray, c_vertex: np.ndarray, c_classes: np.ndarray,
    c_sqnorm: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Query vertex indices and their nearest same-class candidate vertex.

    Returns ``(iq, ic)``; query vertices whose class is absent from the
    candidate are left out.
    """
    if len(q_vertex) == 0 or len(c_vertex) == 0:
        return np.empty(0, np.int64), np.empty(0, np.int64)
    q = np.asarray(q_vertex, dtype=np.float64)
    c = np.asarray(c_vertex, dtype=np.float64)
    cc = np.einsum("ij,ij->i", c, c) if c_sqnorm is None else c_sqnorm
    d2 = np.einsum("ij,ij->i", q, q)[:, None] + cc[None, :] - 2.0 * (q @ c.T)
    same = np.asarray(q_classes)[:, None] == np.asarray(c_classes)[None, :]
    d2 = np.where(same, d2, np.inf)
    ic = np.argmin(d2, axis=1)
    iq = np.flatnonzero(same.any(axis=1))
    return iq, ic[iq].astype(np.int64)


def score_residuals(residuals: np.ndarray, inliers: np.ndarray, settings: VerifySettings) -> float:
    """The named score of a fitted pose (``inf`` when rejected)."""
    n_in = int(inliers.sum())
    if n_in < max(settings.min_inliers, 3):
        return float("inf")
    if settings.score == "clipped-mean":
        return float(np.minimum(residuals, settings.threshold).mean())
    if settings.score == "inlier-mean":
        return float(residuals[inliers].mean())
    raise ValueError(f"unknown score {settings.score!r}; choose from {', '.join(SCORES)}")


def verify_pair(
    q_centroids: np.ndarray, q_classes: np.ndarray, q_vertex: np.ndarray,
    c_centroids: np.ndarray, c_classes: np.ndarray, c_vertex: np.ndarray,
    settings: VerifySettings, rng: np.random.Generator, c_sqnorm: np.ndarray | None = None,
) -> PairResult:
    """Match the vertices of a query and a candidate and score the best rigid fit."""
    iq, ic = class_nearest(q_vertex, q_classes, c_vertex, c_classes, c_sqnorm)
    n = len(iq)
    if n < max(3, settings.min_inliers):
        return PairResult(float("inf"), np.full((4, 4), np.nan), 0, n)
    fit = ransac_rigid(
        np.asarray(c_centroids, dtype=np.float64)[ic],
        np.asarray(q_centroids, dtype=np.float64)[iq],
        threshold=settings.threshold, iterations=settings.iterations,
        min_inliers=settings.min_inliers, rng=rng,
    )
    score = score_residuals(fit.residuals, fit.inliers, settings)
    return PairResult(score, fit.pose, fit.n_inliers, n)
