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

``mapclosures`` is deliberately absent: MapClosures' ground truth
(``tools/gt_closures.py``) is the overlap (>= 0.5) of voxelised (0.5 m) scans
accumulated into local maps every 2 m, so it needs the point clouds, not only
the poses.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import database_limits, revisit_queries_within
from lidar_iris_eval.evaluation.settings import RULES, Convention, Settings

PRESETS: dict[str, Settings] = {
    "liris": Settings(
        name="liris", radius=4.0, exclude=30, distance="3d", pose_frame="camera",
        recall_denominator="revisits",
        source="LiDAR Iris paper (IROS 2020) text: 4 m, E = 30; recall over revisit queries "
               "as in the authors' draw.py"),
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

#: why a requested peer convention is not offered
NOT_OFFERED = {
    "mapclosures": "MapClosures' ground truth is the overlap (>= 0.5) of voxelised local maps "
                   "built from the scans (tools/gt_closures.py), so it cannot be stated from "
                   "poses alone",
}


def get_convention(name: str) -> Settings:
    """The preset called ``name``; an unknown or unavailable name is a LirisError."""
    if name in PRESETS:
        return PRESETS[name]
    if name in NOT_OFFERED:
        raise LirisError(f"--convention {name}", f"not available: {NOT_OFFERED[name]}")
    raise LirisError(f"--convention {name}",
                     f"unknown convention; choose from {', '.join(PRESETS)}")


def with_overrides(conv: Settings, **values) -> Settings:
    """A copy of ``conv`` with the given fields replaced (None values are ignored).

    Setting ``exclude`` clears ``exclude_seconds`` and vice versa, since a
    window is either in frames or in seconds. A changed rule renames the
    copy ``<name>+custom`` unless ``name`` is given.
    """
    given = {k: v for k, v in values.items() if v is not None}
    if "exclude" in given:
        given.setdefault("exclude_seconds", None)
    if given.get("exclude_seconds") is not None:
        given["exclude"] = None
    changed = any(getattr(conv, k) != v for k, v in given.items()
                  if k not in ("name", "source"))
    if changed and "name" not in given:
        given["name"] = f"{conv.name}+custom"
    return conv.replace(**given)


def same_rules(a: Settings, b: Settings) -> bool:
    """True when two conventions differ at most in name and source."""
    return all(getattr(a, k) == getattr(b, k) for k in RULES)


__all__ = ["NOT_OFFERED", "PRESETS", "Convention", "Settings", "convention_counts",
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
    out = {"convention": conv.name, "queries": int(np.count_nonzero(limits >= 0)),
           "revisit_queries": int(np.count_nonzero(revisit))}
    if conv.exclude_seconds is not None:
        out["exclude"] = f"{conv.exclude_seconds:g}s"
        out["window_rule"] = conv.window_rule
    if not conv.last_frame_query:
        out["last_frame_query"] = False
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
    return out
