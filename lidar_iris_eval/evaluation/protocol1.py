"""Protocol 1: loop-closure detection, one best match per query (PROTOCOLS.md).

For each query ``i >= E`` the best database frame ``j* <= i - E`` is found;
a loop is predicted when ``d(i, j*) <= tau`` and it is true when ``j*`` lies
within the radius of ``i``. Queries ``i < E`` have no database and are skipped
(reported as ``n_skipped``). Revisit queries are those with at least one
database frame within the radius; they are the positives.

Recall denominators (named in every output):

* ``revisits`` – recall = TP / #revisit queries. A wrong match on a revisit
  query can never be recovered, so it lowers recall at every threshold.
* ``accepted`` – a revisit query is a false negative only while its best match
  is rejected; a wrong accepted match is only a false positive.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor, yaw_to_pose
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import (
    GroundTruth,
    compute_ground_truth,
    gt_coordinates,
    pair_distances,
)
from lidar_iris_eval.evaluation.metrics import PRCurve, pr_curve, summarize
from lidar_iris_eval.evaluation.poses import (
    pose_errors,
    relative_ground_truth,
    summarize_pose_errors,
    t_columns,
)
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET, BestMatches, best_matches
from lidar_iris_eval.matching.retrieval import two_stage_matches

RECALL_DENOMINATORS = ("revisits", "accepted")
#: heading difference above which a revisit counts as reverse-direction
REVERSE_DEGREES = 90.0


@dataclass(frozen=True)
class Protocol1Result:
    """Per-query table, exact PR curve and summary metrics of protocol 1.

    ``metrics`` holds ``ap, f1_max, f1_threshold, r100p, ep, n_queries,
    n_skipped, n_revisits, n_positives, n_true_top1``, the pose errors
    ``rre_deg_median/p90`` and ``rte_m_median/p90`` of the true matches
    (None when undefined, see ``evaluation/poses.py``) and, when headings
    were given, the same-/reverse-direction breakdown.

    ``pose`` ``(Q, 4, 4)`` is each match's estimated pose (candidate LiDAR
    frame -> query's; NaN where unknown); ``rre_deg``/``rte_m`` its errors.
    """

    matches: BestMatches
    match_dist_m: np.ndarray
    is_revisit: np.ndarray
    is_true: np.ndarray
    is_reverse: np.ndarray | None
    curve: PRCurve
    metrics: dict
    recall_denominator: str
    gt: GroundTruth
    pose: np.ndarray | None = None
    rre_deg: np.ndarray | None = None
    rte_m: np.ndarray | None = None

    def table(self) -> dict[str, np.ndarray]:
        """Columns of ``matches.csv``: query, match, distance, yaw_deg, match_dist_m,
        is_revisit, is_true (plus is_reverse when known), inliers (two-stage),
        rre_deg, rte_m and the 3x4 pose ``T00..T23``."""
        cols = {
            "query": self.matches.query,
            "match": self.matches.match,
            "distance": self.matches.distance,
            "yaw_deg": self.matches.yaw_deg,
            "match_dist_m": self.match_dist_m,
            "is_revisit": self.is_revisit,
            "is_true": self.is_true,
        }
        if self.is_reverse is not None:
            cols["is_reverse"] = self.is_reverse
        if self.matches.inliers is not None:
            cols["inliers"] = self.matches.inliers
        if self.pose is not None:
            cols["rre_deg"] = self.rre_deg
            cols["rte_m"] = self.rte_m
            cols.update(t_columns(self.pose))
        return cols


def check_recall_denominator(name: str) -> None:
    if name not in RECALL_DENOMINATORS:
        raise LirisError(
            f"recall_denominator {name}", f"choose from {', '.join(RECALL_DENOMINATORS)}"
        )


def score_protocol1(
    matches: BestMatches,
    positions: np.ndarray,
    gt: GroundTruth,
    recall_denominator: str = "revisits",
    forward: np.ndarray | None = None,
    lidar_poses: np.ndarray | None = None,
) -> Protocol1Result:
    """Score best matches against ground truth.

    Parameters
    ----------
    matches : best match of each query ``i >= gt.exclude``.
    positions : ``(N, 3)`` translations in ``gt.frame``.
    gt : ground truth under the run's conventions (radius, E, distance, frame).
    recall_denominator : ``revisits`` or ``accepted``.
    forward : optional ``(N, 3)`` unit forward (driving) directions, to split
        revisits into same- and reverse-direction ones.
    lidar_poses : optional ``(N, 4, 4)`` LiDAR-frame poses, for the relative
        pose errors of the matches (``evaluation/poses.py``).
    """
    check_recall_denominator(recall_denominator)
    query, match = matches.query, matches.match
    has = match >= 0
    dist_m = np.full(len(query), np.nan)
    if has.any():
        dist_m[has] = pair_distances(positions, query[has], match[has], gt.frame, gt.distance)
    is_true = has & (dist_m < gt.radius)
    is_revisit = gt.revisit[query]
    discount = (is_revisit & ~is_true) if recall_denominator == "accepted" else None
    curve = pr_curve(matches.distance, is_true, gt.n_revisits, discount=discount)
    metrics = summarize(curve, gt.n_revisits, len(query),
                        f"protocol 1 (E={gt.exclude}, {gt.n_frames} frames, "
                        f"radius {gt.radius:g} m)",
                        "no queries: the exclusion window is at least the sequence length")
    metrics.update(
        n_queries=int(len(query)),
        n_skipped=int(gt.n_frames - len(query)),
        n_revisits=gt.n_revisits,
        n_positives=gt.n_revisits,
        n_true_top1=int(np.count_nonzero(is_true)),
    )
    is_reverse = None
    if forward is not None:
        reverse_all = reverse_revisits(positions, gt, forward)
        is_reverse = reverse_all[query]
        metrics.update(_direction_breakdown(matches, is_true, is_revisit, is_reverse,
                                            metrics["f1_threshold"]))
    pose = rre = rte = None
    if lidar_poses is not None:
        pose = estimated_poses(matches)
        gt_pose = relative_ground_truth(lidar_poses, query, match)
        rre, rte = pose_errors(pose, gt_pose)
        metrics.update(summarize_pose_errors(rre, rte, is_true))
        if is_reverse is not None:  # a 180-degree slip shows here, not in the median
            for label, subset in (("same", ~is_reverse), ("reverse", is_reverse)):
                part = summarize_pose_errors(rre, rte, is_true & subset)
                metrics[f"rre_deg_median_{label}"] = part["rre_deg_median"]
                metrics[f"rre_deg_p90_{label}"] = part["rre_deg_p90"]
    return Protocol1Result(matches, dist_m, is_revisit, is_true, is_reverse, curve, metrics,
                           recall_denominator, gt, pose, rre, rte)


def estimated_poses(matches: BestMatches) -> np.ndarray:
    """``(Q, 4, 4)`` poses of the matches: the method's own, else yaw-only from ``yaw_deg``."""
    if matches.pose is not None:
        pose = np.array(matches.pose, dtype=np.float64)
    else:
        pose = yaw_to_pose(matches.yaw_deg)
    pose[matches.match < 0] = np.nan
    return pose


def reverse_revisits(positions: np.ndarray, gt: GroundTruth, forward: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: revisit queries travelling opposite to their nearest earlier positive.

    For each revisit query ``i`` the nearest database frame ``j <= i - E``
    within the radius is found; the revisit is reverse-direction when the
    angle between the two forward vectors exceeds 90 degrees.
    """
    n = gt.n_frames
    out = np.zeros(n, dtype=bool)
    pairs = gt.pairs
    if len(pairs) == 0:
        return out
    early, late = pairs[:, 0], pairs[:, 1]
    ok = late - early >= gt.exclude
    early, late = early[ok], late[ok]
    if len(late) == 0:
        return out
    coords = gt_coordinates(positions, gt.frame, gt.distance)
    dist = np.linalg.norm(coords[late] - coords[early], axis=1)
    order = np.lexsort((early, dist, late))  # by query, then distance, then index
    late, early = late[order], early[order]
    first = np.unique(late, return_index=True)[1]
    q, j = late[first], early[first]
    fwd = np.asarray(forward, dtype=np.float64)
    fwd = fwd / np.linalg.norm(fwd, axis=1, keepdims=True)
    cos = np.clip(np.sum(fwd[q] * fwd[j], axis=1), -1.0, 1.0)
    out[q] = np.degrees(np.arccos(cos)) > REVERSE_DEGREES
    return out


def _direction_breakdown(matches, is_true, is_revisit, is_reverse, tau) -> dict:
    """Top-1 accuracy and recall at the max-F1 threshold, same vs reverse direction."""
    accepted = matches.distance <= tau if np.isfinite(tau) else np.zeros(len(is_true), bool)
    out = {}
    for label, subset in (("same", is_revisit & ~is_reverse), ("reverse", is_revisit & is_reverse)):
        n = int(np.count_nonzero(subset))
        out[f"n_revisits_{label}"] = n
        out[f"top1_{label}"] = float(np.mean(is_true[subset])) if n else float("nan")
        hits = is_true[subset] & accepted[subset]
        out[f"recall_at_f1_{label}"] = float(np.mean(hits)) if n else float("nan")
    return out


def stacked_descriptors(descriptors, positions: np.ndarray) -> np.ndarray:
    """The stacked array of ``descriptors`` (an array or a DescriptorDB), one per position."""
    descriptors = getattr(descriptors, "descriptors", descriptors)
    if len(positions) != len(descriptors):
        raise LirisError("positions", f"{len(positions)} positions for {len(descriptors)} scans")
    return descriptors


def protocol1(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    positions: np.ndarray,
    *,
    exclude: int = 30,
    radius: float = 4.0,
    distance: str = "3d",
    frame: str = "camera",
    recall_denominator: str = "revisits",
    candidates: int | None = None,
    forward: np.ndarray | None = None,
    pair_budget: int = DEFAULT_PAIR_BUDGET,
    progress: Callable[[int], object] | None = None,
    lidar_poses: np.ndarray | None = None,
) -> Protocol1Result:
    """Run protocol 1 end to end on stacked descriptors and positions.

    ``descriptors`` is the stacked array (or ragged features) or a
    :class:`~lidar_iris_eval.extract.DescriptorDB`. ``candidates=K`` uses
    the descriptor's retrieval stage and verification
    (:mod:`~lidar_iris_eval.matching.retrieval`) instead of the exhaustive
    search; two-stage methods always do, with ``K`` defaulting to
    ``descriptor.default_candidates()``.
    """
    check_recall_denominator(recall_denominator)
    descriptors = stacked_descriptors(descriptors, positions)
    gt = compute_ground_truth(positions, radius, exclude, distance, frame)
    if candidates is not None or descriptor.two_stage:
        k = candidates if candidates is not None else descriptor.default_candidates()
        matches = two_stage_matches(descriptor, descriptors, exclude, k, progress)
    else:
        matches = best_matches(descriptor, descriptors, exclude, pair_budget, progress)
    return score_protocol1(matches, positions, gt, recall_denominator, forward, lidar_poses)
