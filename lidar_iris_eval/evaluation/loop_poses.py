"""Loop poses a back end can use: registration recall, refinement, registration-checked ground
truth (issue 23; conventions in docs/loop-poses.md).

* **Registration recall** (:func:`registration_recall`): over the *true* top-1
  matches (the rows the pose medians use), the share whose pose error is
  within ``(rte_m, rre_deg)`` (default 2 m, 5 deg), with the mean errors over
  those successes. A true match without a pose estimate counts as a failure.
  For yaw-only methods (no translation) the rule is rotation only and named
  ``rotation-only``. No pose estimate at all: None ("n/a").
* **Refinement** (:func:`refine_loops`, ``--refine gicp``): every top-1 match
  with a candidate is registered (:mod:`lidar_iris_eval.matching.registration`)
  from the method's own estimate; the method's pose is kept, the refined pose,
  its fitness and the time are added. An optional acceptance rule
  (``min_inlier_ratio``, ``max_rmse_m``) rejects a match whose fitness is
  poor: its distance becomes ``inf`` (never predicted) and protocol 1 is
  scored again ("descriptor, then ICP check").
* **Ground truth checked by registration** (``gt_pose="refined"``): the
  dataset's relative pose of each true match is the initial guess of a
  registration whose result replaces it as the reference of a second set of
  pose errors (keys ending ``_refined_gt``); the dataset figures stay.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from lidar_iris_eval.errors import LirisError, option
from lidar_iris_eval.evaluation.poses import (
    pose_errors,
    relative_ground_truth,
    summarize_pose_errors,
    t_columns,
)
from lidar_iris_eval.matching.geometry import rotation_error_deg, translation_error_m
from lidar_iris_eval.matching.registration import (
    METHODS,
    RefinedPoses,
    RegistrationSettings,
    ScanCache,
    has_points,
    refine_many,
)

GT_POSES = ("dataset", "refined")
RR_DEFAULT = (2.0, 5.0)
NO_POINTS = "n/a: the sequence holds objects, not point clouds; nothing to register"


@dataclass(frozen=True)
class LoopPoseSettings:
    """What issue 23 adds to a protocol 1 run (all off by default).

    Parameters
    ----------
    refine : None, ``"gicp"`` or ``"icp"``.
    gt_pose : ``"dataset"`` or ``"refined"`` (ground truth checked by registration).
    rr_rte_m, rr_rre_deg : registration recall thresholds.
    min_inlier_ratio, max_rmse_m : the acceptance rule on the refinement's
        fitness (None: no rule).
    registration : registration parameters (the method is ``refine``'s, or
        ``gicp`` for the ground truth alone).
    """

    refine: str | None = None
    gt_pose: str = "dataset"
    rr_rte_m: float = RR_DEFAULT[0]
    rr_rre_deg: float = RR_DEFAULT[1]
    min_inlier_ratio: float | None = None
    max_rmse_m: float | None = None
    registration: RegistrationSettings = field(default_factory=RegistrationSettings)

    def __post_init__(self) -> None:
        if self.refine is not None and self.refine not in METHODS:
            raise LirisError(option("refine", self.refine),
                             f"choose from {', '.join(METHODS)}")
        if self.gt_pose not in GT_POSES:
            raise LirisError(option("gt_pose", self.gt_pose), f"choose from {', '.join(GT_POSES)}")
        for name in ("rr_rte_m", "rr_rre_deg"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise LirisError(option("rr_thresholds", v), "thresholds must be > 0")
        if self.min_inlier_ratio is not None and not 0 <= self.min_inlier_ratio <= 1:
            raise LirisError(option("min_inlier_ratio", self.min_inlier_ratio),
                             "must lie in [0, 1]")
        if self.max_rmse_m is not None and not self.max_rmse_m > 0:
            raise LirisError(option("max_rmse_m", self.max_rmse_m), "must be > 0")
        if self.refine is None and (self.min_inlier_ratio is not None
                                    or self.max_rmse_m is not None):
            raise LirisError(option("min_inlier_ratio", self.min_inlier_ratio),
                             "the acceptance rule needs --refine")
        method = self.refine or "gicp"
        if self.registration.method != method:
            object.__setattr__(self, "registration", replace(self.registration, method=method))
        self.registration.check()

    @property
    def registers(self) -> bool:
        return self.refine is not None or self.gt_pose == "refined"

    def acceptance_rule(self) -> str | None:
        parts = []
        if self.min_inlier_ratio is not None:
            parts.append(f"inlier_ratio >= {self.min_inlier_ratio:g}")
        if self.max_rmse_m is not None:
            parts.append(f"rmse_m <= {self.max_rmse_m:g}")
        return " and ".join(parts) if parts else None

    def config(self) -> dict:
        """The ``config.yaml`` entry (replayed by ``--config``)."""
        return {"loop_poses": {
            "refine": self.refine, "gt_pose": self.gt_pose,
            "rr_thresholds": [self.rr_rte_m, self.rr_rre_deg],
            "min_inlier_ratio": self.min_inlier_ratio, "max_rmse_m": self.max_rmse_m}}

    def conventions(self) -> dict:
        """The metrics.json header entries."""
        out = {
            "registration_recall": f"share of true top-1 matches with rte_m < {self.rr_rte_m:g} "
                                   f"and rre_deg < {self.rr_rre_deg:g} (a true match without a "
                                   "pose fails); rotation-only (rre_deg alone) for yaw-only "
                                   "methods; rr_*_mean over the successes",
            "gt_pose": self.gt_pose,
        }
        if self.registers:
            out["registration"] = self.registration.describe()
        if self.refine is not None:
            out["refine"] = self.refine
            out["acceptance_rule"] = self.acceptance_rule()
        return out


def registration_recall(rre: np.ndarray | None, rte: np.ndarray | None, mask: np.ndarray,
                        rte_m: float = RR_DEFAULT[0], rre_deg: float = RR_DEFAULT[1],
                        prefix: str = "") -> dict:
    """RR over the rows in ``mask`` (rules in the module docstring); keys ``{prefix}rr...``."""
    mask = np.asarray(mask, dtype=bool)
    keys = ("rr", "rr_kind", "rr_rte_m_mean", "rr_rre_deg_mean", "n_rr")
    out: dict = {f"{prefix}{k}": None for k in keys}
    out[f"{prefix}n_rr"] = int(np.count_nonzero(mask))
    if rre is None or not np.isfinite(np.asarray(rre, float)).any():
        return out  # no pose estimate at all: n/a
    rre = np.asarray(rre, dtype=np.float64)
    rte = np.full_like(rre, np.nan) if rte is None else np.asarray(rte, dtype=np.float64)
    full = bool(np.isfinite(rte).any())
    r, t = rre[mask], rte[mask]
    ok = np.isfinite(r) & (r < rre_deg)
    if full:
        ok &= np.isfinite(t) & (t < rte_m)
    out[f"{prefix}rr_kind"] = "full" if full else "rotation-only"
    if not mask.any():
        return out
    out[f"{prefix}rr"] = float(np.mean(ok))
    if ok.any():
        out[f"{prefix}rr_rre_deg_mean"] = float(np.mean(r[ok]))
        if full:
            out[f"{prefix}rr_rte_m_mean"] = float(np.mean(t[ok]))
    return out


@dataclass(frozen=True)
class LoopPoses:
    """Registration results of one descriptor's protocol 1 matches.

    ``refined`` registers every match (None without ``--refine``);
    ``accepted`` is the acceptance rule's verdict per row (all True without a
    rule, False where the registration failed and a rule is set);
    ``gt_refined`` ``(Q, 4, 4)`` the registration-checked ground truth of the
    true matches (NaN elsewhere; None unless ``gt_pose="refined"``).
    """

    settings: LoopPoseSettings
    refined: RefinedPoses | None
    refined_rre: np.ndarray | None
    refined_rte: np.ndarray | None
    accepted: np.ndarray | None
    gt: np.ndarray
    gt_refined: RefinedPoses | None
    n_scans_prepared: int = 0
    #: the descriptor distances before the acceptance rule
    distance: np.ndarray | None = None
    #: downsampling time of the ``n_scans_prepared`` scans, seconds
    prepare_s: float = 0.0

    def columns(self) -> dict[str, np.ndarray]:
        """Extra ``matches.csv`` columns (after the method's own ``T00..T23``)."""
        cols: dict[str, np.ndarray] = {}
        if self.refined is not None:
            r = self.refined
            cols["inlier_ratio"] = r.inlier_ratio
            cols["rmse_m"] = r.rmse_m
            cols["registration_s"] = r.seconds
            cols["registration_accepted"] = np.asarray(self.accepted).astype(np.int8)
            if self.settings.acceptance_rule() is not None:  # distance is inf where rejected
                cols["descriptor_distance"] = self.distance
            cols["refined_rre_deg"] = self.refined_rre
            cols["refined_rte_m"] = self.refined_rte
            cols.update({f"refined_{k}": v for k, v in t_columns(r.pose).items()})
        if self.gt_refined is not None:
            cols.update({f"gt_refined_{k}": v for k, v in t_columns(self.gt_refined.pose).items()})
        return cols


def refine_loops(p1, sequence, settings: LoopPoseSettings,
                 progress: Callable[[int], object] | None = None,
                 cache: ScanCache | None = None, executor=None) -> LoopPoses:
    """Register ``p1``'s matches and/or its true matches' ground truth (see module doc).

    Both registrations run as one :func:`~lidar_iris_eval.matching.registration.refine_many`
    call (a scan is prepared once for both), in parallel on ``executor``'s processes.
    """
    return refine_loops_many([p1], sequence, settings, progress, cache, executor)[0]


def refine_loops_many(p1s: list, sequence, settings: LoopPoseSettings,
                      progress: Callable[[int], object] | None = None,
                      cache: ScanCache | None = None, executor=None) -> list[LoopPoses | None]:
    """:func:`refine_loops` of several methods' protocol 1 results in one registration call.

    Every method's loops share the prepared scans (each prepared once for the
    run, not once per method), and a pair registered from the same start by two
    methods (M2DP and ESF: both from the identity) is registered once. None
    in ``p1s`` gives None. ``n_scans_prepared`` and ``prepare_s`` are the run's.
    """
    if not has_points(sequence):
        raise LirisError(option("refine", settings.refine or settings.gt_pose), NO_POINTS)
    cache = cache if cache is not None else ScanCache(sequence, settings.registration)
    passes, plans = [], []
    for p1 in p1s:
        if p1 is None:
            plans.append(None)
            continue
        m = p1.matches
        gt = relative_ground_truth(sequence.poses, m.query, m.match)
        plans.append(gt)
        if settings.refine is not None:
            passes.append((m.query, m.match, p1.pose))
        if settings.gt_pose == "refined":
            true = np.asarray(p1.is_true, dtype=bool)
            passes.append((m.query, np.where(true, m.match, -1), gt))
    results = refine_many(sequence, passes, settings.registration, progress, cache, executor)
    out: list[LoopPoses | None] = []
    for p1, gt in zip(p1s, plans, strict=True):
        if p1 is None:
            out.append(None)
            continue
        m = p1.matches
        refined = rre = rte = accepted = None
        if settings.refine is not None:
            refined = results.pop(0)
            rre, rte = pose_errors(refined.pose, gt)
            accepted = np.ones(len(m.query), dtype=bool)
            if settings.min_inlier_ratio is not None:
                accepted &= (np.nan_to_num(refined.inlier_ratio, nan=-1.0)
                             >= settings.min_inlier_ratio)
            if settings.max_rmse_m is not None:
                accepted &= np.nan_to_num(refined.rmse_m, nan=np.inf) <= settings.max_rmse_m
        gt_refined = results.pop(0) if settings.gt_pose == "refined" else None
        out.append(LoopPoses(settings, refined, rre, rte, accepted, gt, gt_refined,
                             cache.n_prepared, np.asarray(m.distance).copy(), cache.prepare_s))
    return out


def rescore_with_acceptance(p1, loops: LoopPoses, positions: np.ndarray,
                            forward: np.ndarray | None, lidar_poses: np.ndarray,
                            run_settings=None):
    """Protocol 1 again with rejected matches' distances set to ``inf`` (or ``p1`` itself).

    ``run_settings`` (the run's :class:`~lidar_iris_eval.evaluation.settings.Settings`)
    carries every protocol 1 rule of the convention; without it, the standard rules and
    ``p1``'s recall denominator.
    """
    from lidar_iris_eval.evaluation.protocol1 import score_protocol1, scoring_rules

    if loops.accepted is None or loops.settings.acceptance_rule() is None:
        return p1
    distance = np.where(loops.accepted, p1.matches.distance, np.inf)
    matches = replace(p1.matches, distance=distance)
    rules = (scoring_rules(run_settings) if run_settings is not None
             else {"recall_denominator": p1.recall_denominator})
    return score_protocol1(matches, positions, p1.gt, forward=forward, lidar_poses=lidar_poses,
                           **rules)


def apply(p1, sequence, positions: np.ndarray, forward: np.ndarray | None,
          settings: LoopPoseSettings, desc_name: str = "", progress: bool = False,
          run_settings=None, executor=None, loops: LoopPoses | None = None):
    """``(protocol 1 result, LoopPoses or None)`` after the registrations ``settings`` ask for.

    Without registration, or on a sequence without point clouds (n/a), ``p1``
    is returned as is with None. ``loops``: registrations already made
    (:func:`register_all`), used instead of registering here.
    """
    if not settings.registers or not has_points(sequence):
        return p1, None
    if loops is None:
        loops = register_all([p1], sequence, settings, desc_name, progress, executor)[0]
    return rescore_with_acceptance(p1, loops, positions, forward, sequence.poses,
                                   run_settings), loops


def register_all(p1s: list, sequence, settings: LoopPoseSettings, desc_name: str = "",
                 progress: bool = False, executor=None) -> list[LoopPoses | None]:
    """:func:`refine_loops_many` behind one progress bar (None where nothing is registered)."""
    if not settings.registers or not has_points(sequence) or all(p is None for p in p1s):
        return [None] * len(p1s)
    import sys

    from tqdm import tqdm

    rows = sum(len(p1.matches.query) for p1 in p1s if p1 is not None)  # a tick per row, pass
    total = rows * ((settings.refine is not None) + (settings.gt_pose == "refined"))
    with tqdm(total=total, desc=f"{desc_name} registration", unit="loop", file=sys.stderr,
              disable=not progress, leave=False) as bar:
        return refine_loops_many(p1s, sequence, settings, bar.update, executor=executor)


def _summary(rre, rte, mask, prefix: str, settings: LoopPoseSettings) -> dict:
    out = {f"{prefix}{k}": v for k, v in summarize_pose_errors(rre, rte, mask).items()}
    out.update(registration_recall(rre, rte, mask, settings.rr_rte_m, settings.rr_rre_deg,
                                   prefix))
    return out


def loop_pose_metrics(p1, loops: LoopPoses | None, settings: LoopPoseSettings,
                      n_frames: int | None = None, points: bool = True) -> dict:
    """The metric-row keys of issue 23 for one descriptor (None where undefined).

    Always: registration recall of the method's poses. With ``--refine``: the
    refined poses' medians/p90 and RR (``refined_`` keys), registration time
    per loop and the acceptance rule. With ``gt_pose="refined"``: the errors
    of the method's (and refined) poses against the registration-checked
    ground truth (``_refined_gt`` keys) and how far registration moved it.
    """
    is_true = np.asarray(p1.is_true, dtype=bool)
    out = registration_recall(p1.rre_deg, p1.rte_m, is_true, settings.rr_rte_m,
                              settings.rr_rre_deg)
    if settings.refine is not None:
        out["refine"] = settings.refine if points else None
        out["acceptance_rule"] = settings.acceptance_rule()
        if loops is None or loops.refined is None:  # no point clouds: n/a
            out["refine_note"] = NO_POINTS
            return out
        r = loops.refined
        out.update(_summary(loops.refined_rre, loops.refined_rte, is_true, "refined_", settings))
        secs = r.seconds[np.isfinite(r.seconds)]
        out["registration_ms_per_loop"] = float(np.mean(secs) * 1e3) if len(secs) else None
        out["registration_prepare_ms_per_scan"] = (loops.prepare_s / loops.n_scans_prepared * 1e3
                                                   if loops.n_scans_prepared else None)
        out["n_registered"] = int(np.count_nonzero(r.registered))
        out["n_rejected_by_registration"] = (int(np.count_nonzero(~loops.accepted & (
            p1.matches.match >= 0))) if settings.acceptance_rule() else 0)
        ratio = r.inlier_ratio[is_true & r.registered]
        out["inlier_ratio_median_true"] = float(np.median(ratio)) if len(ratio) else None
    if settings.gt_pose == "refined":
        if loops is None or loops.gt_refined is None:
            out["gt_pose_note"] = NO_POINTS
            return out
        ref = loops.gt_refined.pose
        have = is_true & loops.gt_refined.registered
        if p1.pose is not None:
            rre, rte = pose_errors(p1.pose, ref)
            out.update({f"{k}_refined_gt": v for k, v in
                        _summary(rre, rte, have, "", settings).items()})
        if loops.refined is not None:
            rre, rte = pose_errors(loops.refined.pose, ref)
            out.update({f"{k}_refined_gt": v for k, v in
                        _summary(rre, rte, have, "refined_", settings).items()})
        moved_t = np.full(len(have), np.nan)
        moved_r = np.full(len(have), np.nan)
        if have.any():
            moved_t[have] = translation_error_m(ref[have], loops.gt[have])
            moved_r[have] = rotation_error_deg(ref[have], loops.gt[have])
        out["gt_refinement_m_median"] = float(np.median(moved_t[have])) if have.any() else None
        out["gt_refinement_m_max"] = float(np.max(moved_t[have])) if have.any() else None
        out["gt_refinement_deg_median"] = float(np.median(moved_r[have])) if have.any() else None
        out["n_gt_refined"] = int(np.count_nonzero(have))
    return out
