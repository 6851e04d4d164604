"""Peers' evaluation conventions as named presets, and the ground truth they imply.

Papers report loop-closure numbers under different conventions (radius,
exclusion window, which queries count, what a false positive is), so numbers
are only comparable under the same one. ``liris eval --convention NAME`` sets
every ground-truth option to a peer's values; options given explicitly on the
command line still win, and the run records both the preset name and the
values used.

Each preset states the source it follows (facts read from the authors'
evaluation code; no code is taken from it):

* ``liris`` – today's defaults: 4 m (3-D, camera poses), E = 30 frames (the
  LiDAR Iris paper's text), recall over revisit queries (its ``draw.py``).
* ``scancontext-eval`` – Scan Context's ``fast_evaluator`` (gisbi-kim/scancontext_tro,
  ``fast_evaluator/main.m``): a revisit is a database pose closer than 5 m
  (``revisit_criteria = 5``, strict ``<`` in ``isRevisitGlobalLoc.m``) in the
  ground plane (KITTI pose columns 4 and 12, x and z of the camera, in
  ``makeExperience.m``); the database leaves out the 49 most recent frames
  (``exp_poses(1:end-(num_candidates-1))`` with ``num_candidates = 50``), so
  E = 49; the loop stops one frame short, so the last frame is never a query;
  top-1; a wrong accepted match is a false alarm and only rejected revisits
  are misses (recall denominator ``accepted``).
* ``logg3d`` – LoGG3D-Net's ``evaluation/eval_sequence.py`` and
  ``config/eval_config.py`` (csiro-robotics/LoGG3D-Net): ``revisit_criteria
  = 3`` m, ``not_revisit_criteria = 20`` m, ``skip_time = 30`` s. A query is
  evaluated once 30 s have passed since the first scan; its database runs up
  to and including the first scan later than ``t_query - 30 s``; an accepted
  match within 3 m (``<=``) is a TP, beyond 20 m an FP, and in between it is
  neither (the "not a revisit" band); a rejected revisit query is an FN.
  Distances are 3-D between the pose-file translations.
* ``iris-cpp`` – the LiDAR Iris authors' C++ demo: planar 4 m, E = 300.

* ``wild-places-intra`` – Wild-Places ``eval/intra-sequence.py``
  (csiro-robotics/Wild-Places): ``world_thresh = 5`` m (strict ``<``) in the
  ground plane (easting, northing: LiDAR-frame x, y), ``time_thresh = 300``
  s with the database ``embeddings[:tt+1]``, ``tt`` the first scan later
  than ``t_q - 300 s``, and queries only once 300 s have passed (LoGG3D-Net's
  window rule); top-1; a rejected revisit is an FN, a wrong accepted match an
  FP only (denominator ``accepted``). Its Recall@1 is the share of revisit
  queries whose top-1 is within 5 m (``recall_at_1`` of ``--ranking``).
* ``contour-context`` – contour-context ``scripts/pr_mpe.py``
  (lewisjiang/contour-context): ``thres_dist = 5.0`` m, 3-D, between sensor
  poses (columns 3, 7, 11 of its sensor-pose file: LiDAR frame); a revisit
  has a frame ``j < i - 150`` within 5 m, so E = 151; per-query best score;
  recall ``tp / (tp + fn)`` with ``fn`` the revisit queries not accepted
  (denominator ``accepted``). Its revisit test is ``query_ball_point`` (``<=``)
  while a match is true below 5 m (``<``); here both are strict (they differ
  only for a pair exactly 5 m apart).
* ``bevplace-00`` .. ``bevplace-08`` – BEVPlace ``kitti_dataset.py``
  (zjuluolun/BEVPlace, ``evaluateResults``): the database is the first
  ``kitti_seq_split_points[seq]`` frames (00: 3000, 02: 3400, 05: 1000,
  06: 600, 08: 1000), queries are the frames from that point + 200 on,
  positives closer than ``gt_thres = 5`` m (3-D, pose-file translations,
  camera frame); top-1 recall over queries with a positive (``revisits``).

Cross-session presets (``liris eval --query A --database B``; no exclusion
window, :mod:`~lidar_iris_eval.evaluation.cross_session`):

* ``wild-places-inter`` – Wild-Places ``eval/inter-sequence.py`` and
  ``eval/generate_splits/testing_sets.py``: every query sequence against every
  other, positives by ``KDTree.query_radius(r = 3)`` on (easting, northing):
  planar, ``<=`` 3 m; Recall@1..25, Recall@1 %, MRR. Its test-region split of
  the queries is not reproduced: every query scan is evaluated.
* ``pointnetvlad`` – PointNetVLAD's ``generate_test_sets.py`` and
  OpenPlaceRecognition's ``testing.py``: positives within 25 m
  (``query_radius``, ``<=``) in (northing, easting): planar; Recall@N,
  Recall@1 %.

``mapclosures`` is deliberately absent: MapClosures' ground truth
(``tools/gt_closures.py``) is the overlap (>= 0.5) of voxelised (0.5 m) scans
accumulated into local maps every 2 m, so it needs the point clouds, not only
the poses.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import database_limits, revisit_queries_within
from lidar_iris_eval.evaluation.settings import (
    LIRIS,
    Convention,
    Settings,
    same_rules,
    with_overrides,
)

PRESETS: dict[str, Settings] = {
    "liris": LIRIS,  # the defaults of every rule (settings.py)
    "scancontext-eval": Settings(
        name="scancontext-eval", radius=5.0, exclude=49, distance="planar",
        pose_frame="camera", recall_denominator="accepted", last_frame_query=False,
        source="gisbi-kim/scancontext_tro fast_evaluator/main.m (revisit_criteria = 5, "
               "database exp_poses(1:end-(num_candidates-1)), num_candidates = 50, loop to "
               "num_queries - 1), src/isRevisitGlobalLoc.m (strict <), src/makeExperience.m "
               "(pose columns 4 and 12)"),
    "logg3d": Settings(
        name="logg3d", radius=3.0, exclude_seconds=30.0, window_rule="logg3d", distance="3d",
        pose_frame="camera", recall_denominator="accepted", not_revisit_radius=20.0,
        inclusive_radius=True,
        source="csiro-robotics/LoGG3D-Net evaluation/eval_sequence.py and "
               "config/eval_config.py (revisit_criteria = 3, not_revisit_criteria = 20, "
               "skip_time = 30)"),
    "iris-cpp": Settings(
        name="iris-cpp", radius=4.0, exclude=300, distance="planar", pose_frame="camera",
        recall_denominator="revisits",
        source="LiDAR Iris authors' C++ demo: planar distance, 4 m, 300 frames excluded"),
}

#: BEVPlace's database split per KITTI sequence (kitti_dataset.py kitti_seq_split_points)
BEVPLACE_SPLITS = {"00": 3000, "02": 3400, "05": 1000, "06": 600, "08": 1000}
#: BEVPlace's queries start this many frames after the database
BEVPLACE_QUERY_GAP = 200

PRESETS.update({
    "wild-places-intra": Settings(
        name="wild-places-intra", radius=5.0, exclude_seconds=300.0, window_rule="logg3d",
        distance="planar", pose_frame="lidar", recall_denominator="accepted",
        source="csiro-robotics/Wild-Places eval/intra-sequence.py (world_thresh = 5, "
               "time_thresh = 300, database embeddings[:tt+1] with tt the first scan later "
               "than t_q - 300 s, queries once 300 s have passed; easting/northing)"),
    "contour-context": Settings(
        name="contour-context", radius=5.0, exclude=151, distance="3d", pose_frame="lidar",
        recall_denominator="accepted",
        source="lewisjiang/contour-context scripts/pr_mpe.py (thres_dist = 5.0, revisit "
               "j < i - 150, sensor-pose columns 3, 7, 11, fn = revisits not accepted)"),
})
for _seq, _split in BEVPLACE_SPLITS.items():
    PRESETS[f"bevplace-{_seq}"] = Settings(
        name=f"bevplace-{_seq}", radius=5.0, distance="3d", pose_frame="camera",
        recall_denominator="revisits", database_frames=_split,
        query_start=_split + BEVPLACE_QUERY_GAP,
        source=f"zjuluolun/BEVPlace kitti_dataset.py evaluateResults (gt_thres = 5, database "
               f"first kitti_seq_split_points['{_seq}'] = {_split} frames, queries from "
               f"{_split} + 200; pose columns 3, 7, 11)")

#: presets of query/database runs across sessions (no exclusion window)
CROSS_SESSION_PRESETS: dict[str, Settings] = {
    "wild-places-inter": Settings(
        name="wild-places-inter", radius=3.0, distance="planar", pose_frame="lidar",
        inclusive_radius=True,
        source="csiro-robotics/Wild-Places eval/inter-sequence.py and "
               "eval/generate_splits/testing_sets.py (KDTree.query_radius on easting/northing, "
               "eval_thresh = 3; Recall@1..25, Recall@1%, MRR)"),
    "pointnetvlad": Settings(
        name="pointnetvlad", radius=25.0, distance="planar", pose_frame="lidar",
        inclusive_radius=True,
        source="PointNetVLAD generate_test_sets.py (query_radius r = 25 on northing/easting) "
               "as kept by OpenPlaceRecognition testing.py (Recall@N, Recall@1%)"),
}

#: why a requested peer convention is not offered
NOT_OFFERED = {
    "mapclosures": "MapClosures' ground truth is the overlap (>= 0.5) of voxelised local maps "
                   "built from the scans (tools/gt_closures.py), so it cannot be stated from "
                   "poses alone",
}


def get_convention(name: str, cross_session: bool = False) -> Settings:
    """The preset called ``name``; an unknown or unavailable name is a LirisError.

    ``cross_session``: the run is a query/database run, where the
    cross-session presets are allowed too.
    """
    if name in CROSS_SESSION_PRESETS:
        if not cross_session:
            raise LirisError(f"--convention {name}",
                             "a cross-session convention: use it with --query and --database")
        return CROSS_SESSION_PRESETS[name]
    if name in PRESETS:
        return PRESETS[name]
    if name in NOT_OFFERED:
        raise LirisError(f"--convention {name}", f"not available: {NOT_OFFERED[name]}")
    raise LirisError(f"--convention {name}",
                     f"unknown convention; choose from "
                     f"{', '.join([*PRESETS, *CROSS_SESSION_PRESETS])}")


__all__ = ["BEVPLACE_SPLITS", "CROSS_SESSION_PRESETS", "NOT_OFFERED", "PRESETS", "Convention",
           "Settings", "convention_counts",
           "convention_header", "database_limits", "get_convention", "revisit_queries_within",
           "same_rules", "with_overrides"]


def convention_counts(positions: np.ndarray, conv: Convention,
                      times: np.ndarray | None = None) -> dict:
    """Query and revisit counts under ``conv`` (what ``liris gt --convention`` prints).

    ``positions`` are ``(N, 3)`` translations in ``conv.pose_frame``.
    """
    from lidar_iris_eval.evaluation.ground_truth import gt_coordinates

    limits = database_limits(len(positions), conv, times)
    coords = gt_coordinates(positions, conv.pose_frame, conv.distance)
    revisit = revisit_queries_within(coords, limits, conv.radius, conv.inclusive_radius)
    # the same keys whatever the convention, so scripts reading --json need no cases
    out = {"convention": conv.name, "queries": int(np.count_nonzero(limits >= 0)),
           "revisit_queries": int(np.count_nonzero(revisit)),
           "window_rule": None, "last_frame_query": bool(conv.last_frame_query)}
    if conv.exclude_seconds is not None:
        out["exclude"] = f"{conv.exclude_seconds:g}s"
        out["window_rule"] = conv.window_rule
    return out


def convention_header(recorded: dict | None) -> dict:
    """``metrics.json`` convention keys for a convention recorded in ``config.yaml``.

    ``recorded`` is the ``convention`` entry of the config (``preset`` plus
    the :class:`Convention` fields); the keys say in words what differs from
    the ordinary protocol 1.
    """
    if not recorded:
        return {}
    out = {"convention": recorded.get("preset"), "convention_source": recorded.get("source")}
    if recorded.get("exclude_seconds") is not None:
        seconds = recorded["exclude_seconds"]
        out["exclude_seconds"] = seconds
        out["exclude"] = None
        out["exclude_preset"] = "seconds"
        out["window_rule"] = (
            f"query i searches scans with t_j <= t_i - {seconds:g} s"
            if recorded.get("window_rule") == "liris" else
            f"queries once {seconds:g} s have passed; database up to and including the first "
            f"scan later than t_i - {seconds:g} s (LoGG3D-Net)")
    if recorded.get("inclusive_radius"):
        out["positive"] = (f"protocol 1: ground-truth distance <= {recorded.get('radius'):g} m; "
                           f"protocol 2: < {recorded.get('radius'):g} m")
    if recorded.get("not_revisit_radius") is not None:
        out["not_revisit_band"] = (
            f"accepted matches farther than {recorded.get('radius'):g} m and at most "
            f"{recorded['not_revisit_radius']:g} m are neither true nor false positives")
    if recorded.get("last_frame_query") is False:
        out["query_range"] = "the last frame is never a query (Scan Context's evaluator)"
    if recorded.get("database_frames") is not None:
        out["exclude"] = None
        out["exclude_preset"] = "database split"
        out["query_range"] = (f"database: frames 0..{recorded['database_frames'] - 1}; queries: "
                              f"frames from {recorded.get('query_start')} on (no window)")
    return out
