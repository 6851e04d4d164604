"""Protocol 2: all ordered pairs ``(i, j)``, ``i != j`` (the paper's re-identification test).

A pair is positive when its frames are closer than the radius. The PR curve
sweeps a threshold over the affinity matrix. Counts are ordered pairs, as in
the paper (KITTI 00: 68,420 positive, 20,547,720 negative). For a symmetric
descriptor each unordered pair is scored once with weight 2, which gives
exactly the ordered-pair curve at half the sorting cost.

Two-stage methods (retrieval + verification) have no all-pairs distance; their
affinity follows :data:`~lidar_iris_eval.matching.retrieval.PROTOCOL2_RULE`
(each frame's top-K candidates verified, nothing else ever accepted), and the
result says so in ``metrics["protocol2_rule"]``.
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
from lidar_iris_eval.matching.retrieval import (
    PROTOCOL2_RULE,
    two_stage_affinity,
    two_stage_matches,
)

#: protocol 2 rule of global descriptors (written to metrics.json)
ALL_PAIRS_RULE = "all ordered pairs scored by the descriptor distance"


@dataclass(frozen=True)
class Protocol2Result:
    """Affinity, exact PR curve and metrics (``ap, f1_max, f1_threshold, r100p, ep,
    n_pairs, n_positives, n_negatives``)."""

    affinity: Affinity
    curve: PRCurve
    metrics: dict
    gt: GroundTruth


def score_protocol2(affinity: Affinity, gt: GroundTruth, rule: str = ALL_PAIRS_RULE
                    ) -> Protocol2Result:
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
        protocol2_rule=rule,
    )
    return Protocol2Result(affinity, curve, metrics, gt)


def _affinity(descriptor, descriptors, candidates, pair_budget, progress) -> tuple[Affinity, str]:
    if descriptor.two_stage:
        k = candidates if candidates is not None else descriptor.default_candidates()
        return two_stage_affinity(descriptor, descriptors, k, progress), PROTOCOL2_RULE
    affinity, _ = affinity_matrix(descriptor, descriptors, None, pair_budget, progress)
    return affinity, ALL_PAIRS_RULE


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
    candidates: int | None = None,
) -> Protocol2Result:
    """Compute the affinity of stacked descriptors and score it (ground truth from positions).

    ``descriptors`` is the stacked array or a :class:`~lidar_iris_eval.extract.DescriptorDB`.
    ``candidates`` is K of a two-stage method (ignored for global descriptors).
    """
    descriptors = stacked_descriptors(descriptors, positions)
    gt = compute_ground_truth(positions, radius, 1, distance, frame)
    affinity, rule = _affinity(descriptor, descriptors, candidates, pair_budget, progress)
    return score_protocol2(affinity, gt, rule)


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
    lidar_poses: np.ndarray | None = None,
    candidates: int | None = None,
) -> tuple[Protocol1Result, Protocol2Result]:
    """Both protocols from one affinity pass: each distance is computed once.

    Protocol 1's best matches are read from the float64 blocks of the same
    pass, so they equal those of :func:`~lidar_iris_eval.evaluation.protocol1.protocol1`.
    A two-stage method runs its two retrieval passes instead (``candidates``
    = K, default ``descriptor.default_candidates()``).
    Returns ``(Protocol1Result, Protocol2Result)``.
    """
    check_recall_denominator(recall_denominator)
    descriptors = stacked_descriptors(descriptors, positions)
    gt = compute_ground_truth(positions, radius, exclude, distance, frame)
    if descriptor.two_stage:
        k = candidates if candidates is not None else descriptor.default_candidates()
        matches = two_stage_matches(descriptor, descriptors, exclude, k, progress)
        affinity, rule = two_stage_affinity(descriptor, descriptors, k, None), PROTOCOL2_RULE
    else:
        affinity, matches = affinity_matrix(descriptor, descriptors, exclude, pair_budget,
                                            progress)
        rule = ALL_PAIRS_RULE
    p1 = score_protocol1(matches, positions, gt, recall_denominator, forward, lidar_poses)
    return p1, score_protocol2(affinity, gt, rule)
