"""Protocol 2: all ordered pairs ``(i, j)``, ``i != j`` (the paper's re-identification test).

A pair is positive when its frames are closer than the radius. The PR curve
sweeps a threshold over the affinity matrix. Counts are ordered pairs, as in
the paper (KITTI 00: 68,420 positive, 20,547,720 negative). For a symmetric
descriptor each unordered pair is scored once with weight 2, which gives
exactly the ordered-pair curve at half the sorting cost.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import GroundTruth, compute_ground_truth
from lidar_iris_eval.evaluation.metrics import PRCurve, pr_curve, summarize
from lidar_iris_eval.evaluation.protocol1 import (
    Protocol1Result,
    check_recall_denominator,
    score_protocol1,
    stacked_descriptors,
)
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET, Affinity, affinity_matrix


@dataclass(frozen=True)
class Protocol2Result:
    """Affinity, exact PR curve and metrics (``ap, f1_max, f1_threshold, r100p, ep,
    n_pairs, n_positives, n_negatives``)."""

    affinity: Affinity
    curve: PRCurve
    metrics: dict
    gt: GroundTruth


def score_protocol2(affinity: Affinity, gt: GroundTruth) -> Protocol2Result:
    """Score an affinity matrix against ground truth over ordered pairs.

    NaN distances (other than the diagonal) are never accepted, so such pairs
    count as rejected; the denominator is still every positive pair.
    """
    matrix = affinity.matrix
    n = gt.n_frames
    if matrix.shape != (n, n):
        raise LirisError("affinity", f"shape {matrix.shape} does not match {n} frames")
    positive = gt.positive_matrix()
    if affinity.symmetric:
        mask = np.triu(np.ones((n, n), dtype=bool), 1)
        weight = 2
    else:
        mask = ~np.eye(n, dtype=bool)
        weight = 1
    curve = pr_curve(matrix[mask], positive[mask], gt.n_positive_pairs, weight=weight)
    metrics = summarize(curve)
    metrics.update(
        n_pairs=n * (n - 1),
        n_positives=gt.n_positive_pairs,
        n_negatives=gt.n_negative_pairs,
    )
    return Protocol2Result(affinity, curve, metrics, gt)


def protocol2(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    positions: np.ndarray,
    *,
    radius: float = 4.0,
    distance: str = "3d",
    frame: str = "camera",
    pair_budget: int = DEFAULT_PAIR_BUDGET,
    progress: Callable[[int], object] | None = None,
) -> Protocol2Result:
    """Compute the affinity of stacked descriptors and score it (ground truth from positions).

    ``descriptors`` is the stacked array or a :class:`~lidar_iris_eval.extract.DescriptorDB`.
    """
    descriptors = stacked_descriptors(descriptors, positions)
    gt = compute_ground_truth(positions, radius, 1, distance, frame)
    affinity, _ = affinity_matrix(descriptor, descriptors, None, pair_budget, progress)
    return score_protocol2(affinity, gt)


def protocols_1_and_2(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    positions: np.ndarray,
    *,
    exclude: int = 30,
    radius: float = 4.0,
    distance: str = "3d",
    frame: str = "camera",
    recall_denominator: str = "revisits",
    forward: np.ndarray | None = None,
    pair_budget: int = DEFAULT_PAIR_BUDGET,
    progress: Callable[[int], object] | None = None,
) -> tuple[Protocol1Result, Protocol2Result]:
    """Both protocols from one affinity pass: each distance is computed once.

    Protocol 1's best matches are read from the float64 blocks of the same
    pass, so they equal those of :func:`~lidar_iris_eval.evaluation.protocol1.protocol1`.
    Returns ``(Protocol1Result, Protocol2Result)``.
    """
    check_recall_denominator(recall_denominator)
    descriptors = stacked_descriptors(descriptors, positions)
    gt = compute_ground_truth(positions, radius, exclude, distance, frame)
    affinity, matches = affinity_matrix(descriptor, descriptors, exclude, pair_budget, progress)
    p1 = score_protocol1(matches, positions, gt, recall_denominator, forward)
    return p1, score_protocol2(affinity, gt)
