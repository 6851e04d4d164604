"""Protocol 1 under a peer's convention (see :mod:`conventions`).

The ordinary protocol 1 (``protocol1.py``) uses one exclusion window in
frames and a strict radius. Peers' evaluators differ in ways that need a
per-query database and a different scoring, done here:

* a window in **seconds**: query ``i`` searches ``j <= limits[i]``, one limit
  per query (:func:`conventions.database_limits`);
* queries that are **not evaluated** (the last frame in Scan Context's loop,
  the first 30 s in LoGG3D-Net) have ``limits[i] = -1``;
* LoGG3D-Net's **"not a revisit" band**: an accepted match between the radius
  and ``not_revisit_radius`` is neither a true nor a false positive (and,
  under the ``accepted`` recall denominator, not a miss either).

With a frame window, a strict radius and no band, the result equals
``protocol1()`` exactly (tested), so this module is a strict generalisation.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.evaluation.conventions import (
    Convention,
    database_limits,
    revisit_queries_within,
)
from lidar_iris_eval.evaluation.ground_truth import (
    GroundTruth,
    gt_coordinates,
    pair_distances,
    positive_pairs,
)
from lidar_iris_eval.evaluation.metrics import PRCurve, pr_curve, summarize
from lidar_iris_eval.evaluation.protocol1 import (
    Protocol1Result,
    reverse_revisits,
    score_protocol1,
    stacked_descriptors,
)
from lidar_iris_eval.matching.blocks import (
    DEFAULT_PAIR_BUDGET,
    BestMatches,
    block_rows,
    warm_up,
)


def best_matches_within(descriptor: Descriptor, descriptors: np.ndarray, limits: np.ndarray,
                        pair_budget: int = DEFAULT_PAIR_BUDGET,
                        progress: Callable[[int], object] | None = None) -> BestMatches:
    """Best match of each query ``i`` (``limits[i] >= 0``) over ``j <= limits[i]``.

    Same rules as the exhaustive search: NaN distances never win, ties go to
    the smallest ``j``, ``-1`` / ``inf`` when nothing is defined.
    """
    limits = np.asarray(limits, dtype=np.int64)
    queries = np.flatnonzero(limits >= 0)
    match = np.full(len(queries), -1, dtype=np.int64)
    dist = np.full(len(queries), np.inf)
    yaw = np.full(len(queries), np.nan)
    evaluations = 0
    rows = block_rows(len(descriptors), pair_budget)
    warm_up(descriptor, descriptors)  # compilation is not matching cost
    start = time.perf_counter()
    for a in range(0, len(queries), rows):
        q = queries[a : a + rows]
        lim = limits[q]
        database = descriptors[: int(lim.max()) + 1]
        d, y = descriptor.pairwise(descriptors[q], database)
        d = np.asarray(d, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        evaluations += d.size
        allowed = np.arange(d.shape[1])[None, :] <= lim[:, None]
        masked = np.where(allowed & ~np.isnan(d), d, np.inf)
        best = np.argmin(masked, axis=1)
        value = masked[np.arange(len(q)), best]
        found = np.isfinite(value)
        k = slice(a, a + len(q))
        match[k] = np.where(found, best, -1)
        dist[k] = value
        yaw[k] = np.where(found, y[np.arange(len(q)), best], np.nan)
        if progress is not None:
            progress(len(q))
    seconds = time.perf_counter() - start
    return BestMatches(queries, match, dist, yaw, seconds, evaluations, "exhaustive")


def protocol1_convention(
    descriptor: Descriptor,
    descriptors: np.ndarray,
    positions: np.ndarray,
    conv: Convention,
    *,
    times: np.ndarray | None = None,
    forward: np.ndarray | None = None,
    pair_budget: int = DEFAULT_PAIR_BUDGET,
    progress: Callable[[int], object] | None = None,
) -> Protocol1Result:
    """Protocol 1 end to end under ``conv`` (``positions`` in ``conv.pose_frame``)."""
    descriptors = stacked_descriptors(descriptors, positions)
    limits = database_limits(len(positions), conv, times)
    matches = best_matches_within(descriptor, descriptors, limits, pair_budget, progress)
    return score_convention(matches, positions, limits, conv, forward)


def convention_ground_truth(positions: np.ndarray, limits: np.ndarray,
                            conv: Convention) -> GroundTruth:
    """A :class:`GroundTruth` whose revisit queries follow ``conv``'s per-query database.

    ``exclude`` holds the smallest frame gap any query is allowed (for the
    record; the per-query limits are what count).
    """
    coords = gt_coordinates(positions, conv.pose_frame, conv.distance)
    revisit = revisit_queries_within(coords, limits, conv.radius, conv.inclusive_radius)
    index = np.arange(len(limits))
    gaps = (index - limits)[limits >= 0]
    return GroundTruth(
        n_frames=len(coords), radius=float(conv.radius),
        exclude=int(gaps.min()) if len(gaps) else 0, distance=conv.distance,
        frame=conv.pose_frame, pairs=positive_pairs(coords, conv.radius), revisit=revisit)


def score_convention(matches: BestMatches, positions: np.ndarray, limits: np.ndarray,
                     conv: Convention, forward: np.ndarray | None = None) -> Protocol1Result:
    """Score best matches under ``conv`` (see the module docstring)."""
    gt = convention_ground_truth(positions, limits, conv)
    if conv.not_revisit_radius is None and not conv.inclusive_radius:
        return score_protocol1(matches, positions, gt, conv.recall_denominator, forward)
    else:
        query, match = matches.query, matches.match
        has = match >= 0
        dist_m = np.full(len(query), np.nan)
        if has.any():
            dist_m[has] = pair_distances(positions, query[has], match[has], gt.frame,
                                         gt.distance)
        near = dist_m <= conv.radius if conv.inclusive_radius else dist_m < conv.radius
        is_true = has & near
        band = np.zeros(len(query), dtype=bool)
        if conv.not_revisit_radius is not None:
            band = has & ~is_true & (dist_m <= conv.not_revisit_radius)
        is_revisit = gt.revisit[query]
        curve = band_curve(matches.distance, is_true, band, is_revisit, gt.n_revisits,
                           conv.recall_denominator)
        metrics = summarize(curve)
        metrics.update(n_queries=int(len(query)), n_skipped=int(gt.n_frames - len(query)),
                       n_revisits=gt.n_revisits, n_positives=gt.n_revisits,
                       n_true_top1=int(np.count_nonzero(is_true)),
                       n_band=int(np.count_nonzero(band)))
        result = Protocol1Result(matches, dist_m, is_revisit, is_true, None, curve, metrics,
                                 conv.recall_denominator, gt)
    if forward is not None:  # the direction split of matches.csv (no per-direction metrics)
        is_reverse = reverse_revisits(positions, gt, forward)[matches.query]
        result = Protocol1Result(result.matches, result.match_dist_m, result.is_revisit,
                                 result.is_true, is_reverse, result.curve, result.metrics,
                                 result.recall_denominator, gt)
    return result


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
