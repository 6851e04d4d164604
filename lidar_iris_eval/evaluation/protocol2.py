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
    match_with_band,
    protocol1_inputs,
    score_protocol1,
    scoring_rules,
    settings_from,
    stacked_descriptors,
    with_band,
    with_estimated_poses,
)
from lidar_iris_eval.evaluation.settings import Settings
from lidar_iris_eval.evaluation.streaming_pr import (
    PR_COUNTING,
    StreamedAffinity,
    stream_protocol2,
)
from lidar_iris_eval.matching.blocks import Affinity, affinity_matrix
from lidar_iris_eval.matching.retrieval import (
    PROTOCOL2_RULE,
    two_stage_affinity,
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


def score_protocol2(affinity: Affinity, gt: GroundTruth, rule: str = ALL_PAIRS_RULE,
                    curve: PRCurve | None = None) -> Protocol2Result:
    """Score an affinity matrix against ground truth over ordered pairs.

    NaN distances (other than the diagonal) are never accepted, so such pairs
    count as rejected; the denominator is still every positive pair.
    ``curve``, when given, is the exact curve already counted by the streamed
    pass (:mod:`~lidar_iris_eval.evaluation.streaming_pr`); no matrix is needed.
    """
    n = gt.n_frames
    if curve is None:
        matrix = affinity.matrix
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
    metrics = summarize(curve, gt.n_positive_pairs, n * (n - 1),
                        f"protocol 2 ({n} frames, radius {gt.radius:g} m)",
                        "no pairs: the sequence has fewer than 2 frames")
    metrics.update(
        n_pairs=n * (n - 1),
        n_positives=gt.n_positive_pairs,
        n_negatives=gt.n_negative_pairs,
        protocol2_rule=rule,
    )
    if isinstance(affinity, StreamedAffinity):
        metrics.update(affinity_stored=affinity.storage_note(), pr_counting=PR_COUNTING)
    return Protocol2Result(affinity, curve, metrics, gt)


def _affinity(descriptor, descriptors, candidates, pair_budget, progress) -> tuple[Affinity, str]:
    if descriptor.two_stage:
        k = candidates if candidates is not None else descriptor.default_candidates()
        return two_stage_affinity(descriptor, descriptors, k, progress), PROTOCOL2_RULE
    affinity, _ = affinity_matrix(descriptor, descriptors, None, pair_budget, progress)
    return affinity, ALL_PAIRS_RULE


def _streamed(descriptor, descriptors, gt, limits, pair_budget, progress, storage,
              executor=None):
    """The all-pairs pass of a global descriptor, counted as it goes (O(N + positives)),
    with protocol 1's best matches over ``limits`` (None: protocol 2 only)."""
    return stream_protocol2(descriptor, descriptors, gt.pairs, gt.n_positive_pairs, limits,
                            pair_budget, progress, storage, executor)


def protocol2(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    positions: np.ndarray,
    settings: Settings | None = None,
    *,
    progress: Callable[[int], object] | None = None,
    affinity_storage: str = "auto",
    executor=None,
    **values,
) -> Protocol2Result:
    """Compute the affinity of stacked descriptors and score it (ground truth from positions).

    ``descriptors`` is the stacked array or a :class:`~lidar_iris_eval.extract.DescriptorDB`.
    ``settings`` holds the conventions (the radius, distance and pose frame
    count here; keyword values override them as in
    :func:`~lidar_iris_eval.evaluation.protocol1.protocol1`). ``candidates``
    is K of a two-stage method (ignored for global descriptors).
    ``affinity_storage`` (global descriptors): which affinity to keep, see
    :data:`~lidar_iris_eval.evaluation.streaming_pr.AFFINITY_STORAGE`; the
    metrics are exact whichever is kept.
    """
    s = settings_from(settings, **values)
    descriptors = stacked_descriptors(descriptors, positions)
    gt = compute_ground_truth(positions, s.radius, 1, s.distance, s.pose_frame)
    if not descriptor.two_stage:
        affinity, curve, _ = _streamed(descriptor, descriptors, gt, None, s.pair_budget,
                                       progress, affinity_storage, executor)
        return score_protocol2(affinity, gt, ALL_PAIRS_RULE, curve)
    affinity, rule = _affinity(descriptor, descriptors, s.candidates, s.pair_budget, progress)
    return score_protocol2(affinity, gt, rule)


def protocols_1_and_2(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    positions: np.ndarray,
    settings: Settings | None = None,
    *,
    times: np.ndarray | None = None,
    forward: np.ndarray | None = None,
    progress: Callable[[int], object] | None = None,
    lidar_poses: np.ndarray | None = None,
    affinity_storage: str = "auto",
    executor=None,
    band_limits: np.ndarray | None = None,
    **values,
) -> tuple[Protocol1Result, Protocol2Result]:
    """Both protocols from one pass: protocol 1 and 2 are reducers of the same blocks.

    Protocol 1's best matches over the per-query limits of ``settings`` are
    read from the float64 blocks of the pass that counts protocol 2, so they
    equal those of :func:`~lidar_iris_eval.evaluation.protocol1.protocol1`
    and each distance is computed once. A two-stage method runs its two
    retrieval passes instead (``candidates`` = K, default
    ``descriptor.default_candidates()``); a global descriptor with ``candidates`` set
    takes protocol 1 from the same matcher as
    :func:`~lidar_iris_eval.evaluation.protocol1.protocol1` (its retrieval stage).
    ``band_limits`` (``(K, N)``, ``--convention-band``): protocol 1's best
    matches under each of those limits too, from the same pass.
    Returns ``(Protocol1Result, Protocol2Result)``.
    """
    s, descriptors, limits, gt1 = protocol1_inputs(descriptors, positions, settings, times,
                                                   values)
    gt2 = gt1 if s.standard else compute_ground_truth(positions, s.radius, 1, s.distance,
                                                      s.pose_frame)
    if descriptor.two_stage:
        k = s.candidates if s.candidates is not None else descriptor.default_candidates()
        matches, band = match_with_band(descriptor, descriptors, limits, s, band_limits,
                                        progress, executor)
        affinity, rule = two_stage_affinity(descriptor, descriptors, k, None), PROTOCOL2_RULE
        p1 = score_protocol1(matches, positions, gt1, forward=forward, lidar_poses=lidar_poses,
                            **scoring_rules(s))
        return with_band(p1, band), score_protocol2(affinity, gt2, rule)
    if s.candidates is not None:  # a global descriptor's retrieval stage, as protocol1 runs it
        matches, band = match_with_band(descriptor, descriptors, limits, s, band_limits,
                                        progress, executor)
        p1 = with_band(score_protocol1(matches, positions, gt1, forward=forward,
                                       lidar_poses=lidar_poses, **scoring_rules(s)), band)
        return p1, protocol2(descriptor, descriptors, positions, s.replace(candidates=None),
                             affinity_storage=affinity_storage, executor=executor)
    stacked = limits if band_limits is None else \
        np.vstack([limits[None, :], np.asarray(band_limits, dtype=np.int64)])
    affinity, curve, matches = _streamed(descriptor, descriptors, gt2, stacked, s.pair_budget,
                                         progress, affinity_storage, executor)
    band = None
    if band_limits is not None:
        matches, band = matches[0], tuple(matches[1:])
    matches = with_estimated_poses(descriptor, descriptors, matches)
    p1 = with_band(score_protocol1(matches, positions, gt1, forward=forward,
                                   lidar_poses=lidar_poses, **scoring_rules(s)), band)
    return p1, score_protocol2(affinity, gt2, ALL_PAIRS_RULE, curve)
