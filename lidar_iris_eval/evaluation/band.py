"""Every convention at once (``liris eval --convention-band``, issue 38 item 3).

One protocol 1 matching pass serves every convention preset that applies to
the run: the block pass reduces each block under every preset's per-query
database limits at once (:func:`~lidar_iris_eval.matching.blocks.best_matches`
with ``(K, N)`` limits), so each preset gets exactly the best matches a
separate ``--convention`` run would find, and each is then scored with
:func:`~lidar_iris_eval.evaluation.protocol1.score_protocol1` against its own
ground truth and query set.

Which presets apply (:func:`band_plan`): the single-sequence presets whose
pose frame resolves to the run's (a sequence without camera poses uses
LiDAR-frame poses for ``camera`` presets, as a ``--convention`` run would),
whose window in seconds has scan times, and whose database split (BEVPlace)
is that of the run's KITTI sequence and fits it. Two restrictions per method
(:func:`usable_presets`), because there the matches are not one pass:

* two-stage methods (and ``--candidates``) retrieve their K candidates
  within each query's database, so the best match depends on the window;
  only presets whose limits equal the run's on every query they share are
  kept (their matches are the run's own);
* methods that read local maps bind their map window to E, so their
  descriptors depend on it; only presets with the run's E are kept.

The presets left out, and why, are recorded in the band.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lidar_iris_eval.evaluation.conventions import PRESETS
from lidar_iris_eval.evaluation.ground_truth import database_limits, ground_truth_for
from lidar_iris_eval.evaluation.metrics import PRCurve
from lidar_iris_eval.evaluation.settings import Settings

#: the protocol 1 metrics a band is kept for
BAND_METRICS = ("ap", "f1_max", "r100p", "ep", "n_queries", "n_revisits", "n_true_top1")
#: what the band means (metrics.json header)
BAND_RULE = ("convention_band of a protocol 1 row: each metric under the run's own convention "
             "('own') and its minimum and maximum over the convention presets that apply to "
             "the run (same pose frame; windows in seconds need scan times; BEVPlace splits "
             "only on their KITTI sequence), with the preset of each extreme; 'values' holds "
             "every preset's metrics, 'skipped' the presets left out and why, 'notes' why a "
             "preset's numbers are undefined. All from one "
             "matching pass: each block is reduced under every preset's database limits")


@dataclass(frozen=True)
class BandPlan:
    """The presets of a band, their per-query limits ``(K, N)`` and the presets left out."""

    presets: tuple[Settings, ...]
    limits: np.ndarray
    skipped: dict[str, str] = field(default_factory=dict)


def band_plan(sequence, settings: Settings, pose_frame: str) -> BandPlan:
    """The presets that apply to a run of ``sequence`` under ``settings`` (in ``pose_frame``)."""
    n = len(sequence)
    times = getattr(sequence, "times", None)
    has_camera = getattr(sequence, "camera_poses", None) is not None
    name = str(getattr(sequence, "name", "") or "")
    presets, limits, skipped = [], [], {}
    for preset in PRESETS.values():
        frame = preset.pose_frame if (preset.pose_frame == "lidar" or has_camera) else "lidar"
        if frame != pose_frame:
            skipped[preset.name] = f"pose frame {preset.pose_frame}, the run's is {pose_frame}"
            continue
        if preset.exclude_seconds is not None and times is None:
            skipped[preset.name] = "a window in seconds needs scan times"
            continue
        if preset.database_frames is not None:
            seq = preset.name.rsplit("-", 1)[-1]
            if not (name == seq or name.endswith(f"/{seq}")) or preset.query_start >= n:
                skipped[preset.name] = f"BEVPlace's split of KITTI {seq} only"
                continue
        p = preset.replace(pose_frame=frame, candidates=settings.candidates,
                           pair_budget=settings.pair_budget)
        lim = database_limits(n, p, times)
        if not np.any(lim >= 0):
            skipped[preset.name] = "no queries: its window is at least the sequence length"
            continue
        presets.append(p)
        limits.append(lim)
    stacked = np.stack(limits) if limits else np.zeros((0, n), dtype=np.int64)
    return BandPlan(tuple(presets), stacked, skipped)


def usable_presets(plan: BandPlan, descriptor, settings: Settings,
                   own_limits: np.ndarray) -> tuple[list[int], dict[str, str]]:
    """Indices of ``plan.presets`` one matching pass of ``descriptor`` serves, and the rest
    with the reason (see the module docstring)."""
    two_stage = bool(descriptor.two_stage) or settings.candidates is not None
    local_maps = hasattr(descriptor, "bind_exclusion")
    keep, left = [], {}
    for k, preset in enumerate(plan.presets):
        lim = plan.limits[k]
        if local_maps and (preset.exclude_seconds is not None or preset.exclude != settings.exclude
                           or settings.exclude_seconds is not None):
            left[preset.name] = "its local maps are built over the run's E; another E " \
                                "changes the descriptors"
            continue
        if two_stage:
            shared = (lim >= 0) & (own_limits >= 0)
            if not (np.all(own_limits[lim >= 0] >= 0) and np.array_equal(lim[shared],
                                                                          own_limits[shared])):
                left[preset.name] = "a two-stage method retrieves within each query's " \
                                    "database, so another window needs its own matching pass"
                continue
        keep.append(k)
    return keep, left


def restrict_matches(matches, limits: np.ndarray):
    """The run's own matches on the queries of ``limits`` (presets whose windows equal the
    run's on those queries: same database, same best match)."""
    from dataclasses import replace

    own = limits[matches.query] >= 0
    return replace(matches, query=matches.query[own], match=matches.match[own],
                   distance=matches.distance[own], yaw_deg=matches.yaw_deg[own],
                   pose=None if matches.pose is None else matches.pose[own],
                   inliers=None if matches.inliers is None else matches.inliers[own])


def score_band(band_matches, positions: np.ndarray, presets, limits: np.ndarray,
               times=None) -> tuple[dict[str, dict], dict[str, PRCurve]]:
    """Each preset's protocol 1 metrics and PR curve from its best matches."""
    import warnings

    from lidar_iris_eval.evaluation.protocol1 import score_protocol1, scoring_rules

    values, curves = {}, {}
    for matches, preset, lim in zip(band_matches, presets, limits, strict=True):
        gt = ground_truth_for(positions, preset, times, limits=lim)
        with warnings.catch_warnings(record=True) as caught:  # kept in the band, not printed
            warnings.simplefilter("always")
            scored = score_protocol1(matches, positions, gt, **scoring_rules(preset))
        values[preset.name] = {k: scored.metrics.get(k) for k in BAND_METRICS}
        notes = [str(w.message) for w in caught]
        if notes:
            values[preset.name]["notes"] = notes
        curves[preset.name] = scored.curve
    return values, curves


def band_block(own_row: dict, own_name: str, values: dict[str, dict],
               skipped: dict[str, str]) -> dict:
    """The ``convention_band`` entry of a protocol 1 row (see :data:`BAND_RULE`)."""
    metrics = {}
    for key in BAND_METRICS:
        entry = {"own": _finite(own_row.get(key))}
        defined = {name: v[key] for name, v in values.items() if _finite(v.get(key)) is not None}
        if defined:
            low = min(defined, key=lambda name: defined[name])
            high = max(defined, key=lambda name: defined[name])
            entry.update(min=defined[low], max=defined[high], min_preset=low, max_preset=high)
        else:
            entry.update(min=None, max=None, min_preset=None, max_preset=None)
        metrics[key] = entry
    out = {"own_convention": own_name, "presets": list(values), "metrics": metrics,
           "values": {name: {k: _finite(v.get(k)) for k in BAND_METRICS}
                      for name, v in values.items()},
           "skipped": dict(skipped)}
    notes = {name: v["notes"] for name, v in values.items() if v.get("notes")}
    if notes:  # why a preset's numbers are undefined (e.g. no revisit under its radius)
        out["notes"] = notes
    return out


def _finite(value):
    if value is None or isinstance(value, bool):
        return None
    if isinstance(value, (int, np.integer)):
        return int(value)
    try:
        value = float(value)
    except (TypeError, ValueError):
        return None
    return value if np.isfinite(value) else None
