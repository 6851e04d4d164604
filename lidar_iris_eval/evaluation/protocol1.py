"""Protocol 1: loop-closure detection, one best match per query (PROTOCOLS.md).

One protocol 1 over per-query database limits: query ``i`` may match
``j <= limits[i]`` (``-1``: not a query). The standard rule ``limits[i] =
i - E`` is one case; peers' conventions (a window in seconds, the last frame
never a query, LoGG3D-Net's "not a revisit" band and inclusive radius) are
others, all described by one :class:`~lidar_iris_eval.evaluation.settings.Settings`.
Every method goes through the same matcher (:func:`match_protocol1`): the
exhaustive block pass for global descriptors, retrieval + verification for
two-stage methods (and for ``candidates=K``).

In the standard case: for each query ``i >= E`` the best database frame ``j* <= i - E`` is found;
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

import time
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor, yaw_to_pose
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import (
    GroundTruth,
    database_limits,
    ground_truth_for,
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
from lidar_iris_eval.evaluation.settings import RECALL_DENOMINATORS, Settings
from lidar_iris_eval.matching.blocks import BestMatches, best_matches
from lidar_iris_eval.matching.retrieval import pose_yaw_deg, two_stage_matches

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
    #: ``--convention-band``: the best matches under each band preset's limits, same pass
    band_matches: tuple[BestMatches, ...] | None = None

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
    *,
    inclusive_radius: bool = False,
    not_revisit_radius: float | None = None,
    exclude_seconds: float | None = None,
) -> Protocol1Result:
    """Score best matches against ground truth.

    Parameters
    ----------
    matches : best match of each query (``gt.query_limits() >= 0``).
    positions : ``(N, 3)`` translations in ``gt.frame``.
    gt : ground truth under the run's conventions (radius, E, distance, frame).
    recall_denominator : ``revisits`` or ``accepted``.
    forward : optional ``(N, 3)`` unit forward (driving) directions, to split
        revisits into same- and reverse-direction ones.
    lidar_poses : optional ``(N, 4, 4)`` LiDAR-frame poses, for the relative
        pose errors of the matches (``evaluation/poses.py``).
    inclusive_radius, not_revisit_radius : a match at exactly the radius is true; accepted
        matches closer than ``not_revisit_radius`` but not true are neither true nor false
        (:func:`scoring_rules` takes both from a :class:`Settings`).
    exclude_seconds : the window in seconds, named in the warning on undefined numbers.
    """
    denominator = recall_denominator
    check_recall_denominator(denominator)
    inclusive = bool(inclusive_radius)
    band_radius = not_revisit_radius
    query, match = matches.query, matches.match
    has = match >= 0
    dist_m = np.full(len(query), np.nan)
    if has.any():
        dist_m[has] = pair_distances(positions, query[has], match[has], gt.frame, gt.distance)
    is_true = has & ((dist_m <= gt.radius) if inclusive else (dist_m < gt.radius))
    band = np.zeros(len(query), dtype=bool)
    if band_radius is not None:
        band = has & ~is_true & (dist_m <= band_radius)
    is_revisit = gt.revisit[query]
    discount = (is_revisit & ~is_true) if denominator == "accepted" else None
    if band.any():
        curve = band_curve(matches.distance, is_true, band, is_revisit, gt.n_revisits,
                           denominator)
    else:
        curve = pr_curve(matches.distance, is_true, gt.n_revisits, discount=discount)
    metrics = summarize(curve, gt.n_revisits, len(query), _context(gt, exclude_seconds),
                        "no queries: the exclusion window is at least the sequence length")
    metrics.update(
        n_queries=int(len(query)),
        n_skipped=int(gt.n_frames - len(query)),
        n_revisits=gt.n_revisits,
        n_positives=gt.n_revisits,
        n_true_top1=int(np.count_nonzero(is_true)),
    )
    if band_radius is not None:
        metrics["n_band"] = int(np.count_nonzero(band))
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
                           denominator, gt, pose, rre, rte)


def scoring_rules(settings: Settings) -> dict:
    """The keyword rules of :func:`score_protocol1` under a run's :class:`Settings`."""
    return {"recall_denominator": settings.recall_denominator,
            "inclusive_radius": settings.inclusive_radius,
            "not_revisit_radius": settings.not_revisit_radius,
            "exclude_seconds": settings.exclude_seconds}


def _context(gt: GroundTruth, exclude_seconds: float | None) -> str:
    """Names the evaluation in the warning given when its numbers are undefined."""
    if exclude_seconds is not None:
        window = f"{exclude_seconds:g} s window"
    else:
        window = f"E={gt.exclude}"
    return f"protocol 1 ({window}, {gt.n_frames} frames, radius {gt.radius:g} m)"


def band_curve(distances: np.ndarray, is_true: np.ndarray, band: np.ndarray,
               is_revisit: np.ndarray, n_revisits: int, denominator: str) -> PRCurve:
    """The exact PR curve when ``band`` predictions count as neither TP nor FP.

    With the ``accepted`` denominator an accepted wrong match on a revisit
    query (band or not) removes that query from the denominator; with
    ``revisits`` it stays a miss. Points where only band predictions are
    accepted have no defined precision and are left out.
    """
    distances = np.asarray(distances, dtype=np.float64)
    counted = ~band
    discount = (is_revisit & ~is_true) if denominator == "accepted" else None
    base = pr_curve(distances[counted], is_true[counted], n_revisits,
                    discount=None if discount is None else discount[counted])
    if discount is None or not band.any():
        return base
    # band revisit queries leave the denominator too once accepted
    extra = np.sort(distances[band & discount & np.isfinite(distances)])
    drop = np.searchsorted(extra, base.threshold, side="right")
    denom = base.tp + base.fn - drop
    with np.errstate(invalid="ignore", divide="ignore"):
        recall = np.where(denom > 0, base.tp / np.maximum(denom, 1), np.nan)
    return PRCurve(base.threshold, base.precision, recall.astype(np.float64), base.tp, base.fp,
                   denom - base.tp)


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
    ok = early <= gt.query_limits()[late]
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


def settings_from(settings: Settings | None = None, *, exclude=None, radius=None,
                  distance=None, frame=None, recall_denominator=None, candidates=None,
                  pair_budget=None) -> Settings:
    """``settings`` (default :class:`Settings()`) with the keyword values given (not None)."""
    values = {"exclude": exclude, "radius": radius, "distance": distance, "pose_frame": frame,
              "recall_denominator": recall_denominator, "candidates": candidates,
              "pair_budget": pair_budget}
    values = {k: v for k, v in values.items() if v is not None}
    if "exclude" in values:
        values.setdefault("exclude_seconds", None)
    base = Settings() if settings is None else settings
    return base.replace(**values) if values else base


def protocol1_inputs(descriptors, positions: np.ndarray, settings: Settings | None,
                     times: np.ndarray | None,
                     values: dict) -> tuple[Settings, np.ndarray, np.ndarray, GroundTruth]:
    """What protocol 1 starts from: ``(settings, stacked descriptors, limits, ground truth)``.

    :func:`protocol1` and :func:`~lidar_iris_eval.evaluation.protocol2.protocols_1_and_2`
    both begin here, so their conventions, per-query database limits and
    ground truth cannot drift apart. ``values`` are the keyword overrides of
    :func:`settings_from`.
    """
    settings = settings_from(settings, **values)
    descriptors = stacked_descriptors(descriptors, positions)
    limits = database_limits(len(positions), settings, times)
    return settings, descriptors, limits, ground_truth_for(positions, settings, limits=limits)


def with_estimated_poses(descriptor: Descriptor, descriptors, matches: BestMatches
                         ) -> BestMatches:
    """``matches`` carrying the poses a global descriptor estimates for them
    (:meth:`~lidar_iris_eval.descriptors.base.Descriptor.estimate_poses`), their
    yaw in the descriptor convention and their inliers; the time is matching time.
    Unchanged for a method that estimates none or that already gave poses."""
    estimate = getattr(descriptor, "estimate_poses", None)
    if matches.pose is not None or getattr(descriptor, "two_stage", False) or estimate is None:
        return matches
    began = time.perf_counter()
    out = estimate(descriptors, matches.query, matches.match)
    if out is None:
        return matches
    pose, inliers = np.asarray(out[0], dtype=np.float64), np.asarray(out[1], dtype=np.int64)
    return replace(matches, pose=pose, inliers=inliers, yaw_deg=pose_yaw_deg(pose),
                   seconds=matches.seconds + time.perf_counter() - began)


def match_protocol1(descriptor: Descriptor, descriptors, limits: np.ndarray,
                    settings: Settings, progress: Callable[[int], object] | None = None,
                    executor=None) -> BestMatches:
    """The one matcher: each query's best match over ``j <= limits[i]``.

    Two-stage methods (and ``settings.candidates = K``) retrieve and verify
    (:func:`~lidar_iris_eval.matching.retrieval.two_stage_matches`); global
    descriptors search exhaustively in blocks
    (:func:`~lidar_iris_eval.matching.blocks.best_matches`).
    """
    if settings.candidates is not None or descriptor.two_stage:
        k = settings.candidates if settings.candidates is not None \
            else descriptor.default_candidates()
        return two_stage_matches(descriptor, descriptors, limits, k, progress)
    return with_estimated_poses(descriptor, descriptors, best_matches(
        descriptor, descriptors, limits, settings.pair_budget, progress, executor))


def match_with_band(descriptor: Descriptor, descriptors, limits: np.ndarray,
                    settings: Settings, band_limits: np.ndarray | None,
                    progress: Callable[[int], object] | None = None,
                    executor=None) -> tuple[BestMatches, tuple[BestMatches, ...] | None]:
    """:func:`match_protocol1`, plus the best matches under each row of ``band_limits``
    (``(K, N)``, ``--convention-band``) from the same pass.

    The exhaustive pass reduces every block under all limits at once. A
    two-stage method's band rows must be windows equal to the run's on their
    queries (:func:`~lidar_iris_eval.evaluation.band.usable_presets`): their
    matches are the run's own, restricted to their queries.
    """
    if band_limits is None:
        return match_protocol1(descriptor, descriptors, limits, settings, progress,
                               executor), None
    if settings.candidates is not None or descriptor.two_stage:
        matches = match_protocol1(descriptor, descriptors, limits, settings, progress, executor)
        return matches, tuple(restrict_matches(matches, lim) for lim in band_limits)
    stacked = np.vstack([limits[None, :], np.asarray(band_limits, dtype=np.int64)])
    every = best_matches(descriptor, descriptors, stacked, settings.pair_budget, progress,
                         executor)
    return with_estimated_poses(descriptor, descriptors, every[0]), tuple(every[1:])


def with_band(result: Protocol1Result, band: tuple[BestMatches, ...] | None) -> Protocol1Result:
    """``result`` carrying the band's matches (unchanged when there is no band)."""
    from dataclasses import replace

    return result if band is None else replace(result, band_matches=band)


def protocol1(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    positions: np.ndarray,
    settings: Settings | None = None,
    *,
    times: np.ndarray | None = None,
    forward: np.ndarray | None = None,
    progress: Callable[[int], object] | None = None,
    lidar_poses: np.ndarray | None = None,
    executor=None,
    band_limits: np.ndarray | None = None,
    **values,
) -> Protocol1Result:
    """Run protocol 1 end to end on stacked descriptors and positions.

    ``descriptors`` is the stacked array (or ragged features) or a
    :class:`~lidar_iris_eval.extract.DescriptorDB`; ``positions`` are in
    ``settings.pose_frame``. ``settings`` holds every convention; the keyword
    values ``exclude``, ``radius``, ``distance``, ``frame``,
    ``recall_denominator``, ``candidates`` and ``pair_budget`` override it
    (:func:`settings_from`). ``times`` (seconds per scan) are needed by a
    window in seconds. ``candidates=K`` uses the descriptor's retrieval stage
    and verification instead of the exhaustive search; two-stage methods
    always do, with ``K`` defaulting to ``descriptor.default_candidates()``.
    ``band_limits`` (``(K, N)``): also the best matches under each of those
    limits, from the same pass (``Protocol1Result.band_matches``).
    """
    settings, descriptors, limits, gt = protocol1_inputs(descriptors, positions, settings,
                                                         times, values)
    matches, band = match_with_band(descriptor, descriptors, limits, settings, band_limits,
                                    progress, executor)
    return with_band(score_protocol1(matches, positions, gt, forward=forward,
                                     lidar_poses=lidar_poses, **scoring_rules(settings)), band)


def restrict_matches(matches, limits: np.ndarray):
    """The run's own matches on the queries of ``limits`` (presets whose windows equal the
    run's on those queries: same database, same best match)."""
    from dataclasses import replace

    own = limits[matches.query] >= 0
    return replace(matches, query=matches.query[own], match=matches.match[own],
                   distance=matches.distance[own], yaw_deg=matches.yaw_deg[own],
                   pose=None if matches.pose is None else matches.pose[own],
                   inliers=None if matches.inliers is None else matches.inliers[own])
