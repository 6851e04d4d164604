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

from dataclasses import asdict, dataclass

import numpy as np

from lidar_iris_eval.errors import LirisError


@dataclass(frozen=True)
class Convention:
    """A complete ground-truth convention.

    Attributes
    ----------
    name : preset name.
    radius : metres; a database frame is a true match closer than this.
    exclude : frames (E), or None when the window is in seconds.
    exclude_seconds : seconds, or None when the window is in frames.
    window_rule : ``"liris"`` (database ``t_j <= t_i - T``) or ``"logg3d"``
        (also the first scan after ``t_i - T``, and queries only once ``T``
        has passed since the first scan).
    distance, pose_frame : as ``--distance`` and ``--pose-frame``.
    recall_denominator : ``revisits`` or ``accepted``.
    not_revisit_radius : metres, or None. Accepted matches between
        ``radius`` and this are neither true nor false positives.
    inclusive_radius : a match exactly at ``radius`` is true (LoGG3D's ``<=``).
    last_frame_query : False when the last frame is never a query.
    source : where the values come from.
    """

    name: str
    radius: float
    exclude: int | None
    exclude_seconds: float | None
    window_rule: str
    distance: str
    pose_frame: str
    recall_denominator: str
    not_revisit_radius: float | None
    inclusive_radius: bool
    last_frame_query: bool
    source: str

    @property
    def standard(self) -> bool:
        """True when the ordinary protocol 1 (frame window, strict radius) applies."""
        return (self.exclude_seconds is None and self.not_revisit_radius is None
                and not self.inclusive_radius and self.last_frame_query)

    def to_dict(self) -> dict:
        return asdict(self)


PRESETS: dict[str, Convention] = {
    "liris": Convention(
        "liris", 4.0, 30, None, "liris", "3d", "camera", "revisits", None, False, True,
        "LiDAR Iris paper (IROS 2020) text: 4 m, E = 30; recall over revisit queries as in "
        "the authors' draw.py"),
    "scancontext-eval": Convention(
        "scancontext-eval", 5.0, 49, None, "liris", "planar", "camera", "accepted", None, False,
        False,
        "gisbi-kim/scancontext_tro fast_evaluator/main.m (revisit_criteria = 5, database "
        "exp_poses(1:end-(num_candidates-1)), num_candidates = 50, loop to num_queries - 1), "
        "src/isRevisitGlobalLoc.m (strict <), src/makeExperience.m (pose columns 4 and 12)"),
    "logg3d": Convention(
        "logg3d", 3.0, None, 30.0, "logg3d", "3d", "camera", "accepted", 20.0, True, True,
        "csiro-robotics/LoGG3D-Net evaluation/eval_sequence.py and config/eval_config.py "
        "(revisit_criteria = 3, not_revisit_criteria = 20, skip_time = 30)"),
    "iris-cpp": Convention(
        "iris-cpp", 4.0, 300, None, "liris", "planar", "camera", "revisits", None, False, True,
        "LiDAR Iris authors' C++ demo: planar distance, 4 m, 300 frames excluded"),
}

#: why a requested peer convention is not offered
NOT_OFFERED = {
    "mapclosures": "MapClosures' ground truth is the overlap (>= 0.5) of voxelised local maps "
                   "built from the scans (tools/gt_closures.py), so it cannot be stated from "
                   "poses alone",
}


def get_convention(name: str) -> Convention:
    """The preset called ``name``; an unknown or unavailable name is a LirisError."""
    if name in PRESETS:
        return PRESETS[name]
    if name in NOT_OFFERED:
        raise LirisError(f"--convention {name}", f"not available: {NOT_OFFERED[name]}")
    raise LirisError(f"--convention {name}",
                     f"unknown convention; choose from {', '.join(PRESETS)}")


def with_overrides(conv: Convention, **values) -> Convention:
    """A copy of ``conv`` with the given fields replaced (None values are ignored).

    Setting ``exclude`` clears ``exclude_seconds`` and vice versa, since a
    window is either in frames or in seconds.
    """
    fields = conv.to_dict()
    given = {k: v for k, v in values.items() if v is not None}
    if "exclude" in given:
        fields["exclude_seconds"] = None
    if "exclude_seconds" in given:
        fields["exclude"] = None
    fields.update(given)
    changed = any(fields[k] != getattr(conv, k) for k in given)
    if changed and "name" not in given:
        fields["name"] = f"{conv.name}+custom"
    return Convention(**fields)


def same_rules(a: Convention, b: Convention) -> bool:
    """True when two conventions differ at most in name and source."""
    skip = {"name", "source"}
    return all(getattr(a, k) == getattr(b, k) for k in a.to_dict() if k not in skip)


def database_limits(n_frames: int, conv: Convention, times: np.ndarray | None = None,
                    source: str = "times.txt") -> np.ndarray:
    """``(N,)`` last database index each query may match, ``-1`` when it is not a query.

    Frame windows give ``i - E``. Time windows need ``times`` (seconds, one per
    scan, non-decreasing) and follow ``conv.window_rule`` (see :class:`Convention`).
    """
    index = np.arange(n_frames)
    if conv.exclude_seconds is None:
        if conv.exclude is None or conv.exclude < 1:
            raise LirisError(f"convention {conv.name}", "exclusion window must be at least 1")
        limits = index - int(conv.exclude)
    else:
        if times is None:
            raise LirisError(
                f"--exclude {conv.exclude_seconds:g}s",
                "a window in seconds needs scan times (times.txt beside the scans, --times, "
                "or bag timestamps)")
        times = np.asarray(times, dtype=np.float64)
        if len(times) != n_frames:
            raise LirisError(source, f"{len(times)} times for {n_frames} scans")
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
            raise LirisError(source, "scan times must be finite and non-decreasing")
        seconds = float(conv.exclude_seconds)
        if seconds <= 0:
            raise LirisError(f"--exclude {seconds:g}s", "exclusion window must be positive")
        # last j with t_j <= t_i - T
        limits = np.searchsorted(times, times - seconds, side="right") - 1
        if conv.window_rule == "logg3d":
            limits = np.where(times - times[0] >= seconds, limits + 1, -1)
            limits = np.minimum(limits, index - 1)
    limits = np.where(limits >= 0, limits, -1)
    if not conv.last_frame_query and n_frames:
        limits[-1] = -1
    return limits.astype(np.int64)


def revisit_queries_within(coords: np.ndarray, limits: np.ndarray, radius: float,
                           inclusive: bool = False) -> np.ndarray:
    """``(N,)`` bool: query ``i`` has a database frame ``j <= limits[i]`` within ``radius``.

    ``coords`` are the ground-truth coordinates (see ``ground_truth.gt_coordinates``).
    """
    from scipy.spatial import cKDTree

    coords = np.asarray(coords, dtype=np.float64)
    n = len(coords)
    revisit = np.zeros(n, dtype=bool)
    if n < 2:
        return revisit
    # query_pairs is inclusive (<= r); trim to strict unless asked
    pairs = cKDTree(coords).query_pairs(radius, output_type="ndarray").astype(np.int64)
    if len(pairs) == 0:
        return revisit
    pairs.sort(axis=1)
    if not inclusive:
        dist = np.linalg.norm(coords[pairs[:, 0]] - coords[pairs[:, 1]], axis=1)
        pairs = pairs[dist < radius]
    early, late = pairs[:, 0], pairs[:, 1]
    ok = early <= limits[late]
    revisit[late[ok]] = True
    return revisit


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
