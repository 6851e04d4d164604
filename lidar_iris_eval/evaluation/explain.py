"""Why a pair is (not) a loop, and what two conventions disagree on.

``liris gt SEQ --explain I J`` and ``liris gt SEQ --diff A B`` are answered
here. Nothing below restates a counting rule: every verdict is read from the
functions that count (:func:`~lidar_iris_eval.evaluation.ground_truth.database_limits`
for which frames a query may match, :func:`~.ground_truth.within_radius`
for the radius test, :func:`~.ground_truth.revisit_queries_within` for the
revisit flag and :func:`~.ground_truth.ground_truth_for` for the positive
pairs), so an explanation can never disagree with a count. What is added is
only the *name* of the rule that decided:

* ``radius`` – the pose distance is not within the preset's radius;
* ``E`` – the frames are fewer than E apart (a window in frames);
* ``window`` – a window in seconds (the scan times) leaves the frame out;
* ``database split`` – BEVPlace's fixed database / query ranges;
* ``last frame`` – Scan Context's evaluator never queries the last frame;
* ``frame`` – the preset measures in a pose frame the input does not have
  (LiDAR-frame presets on camera poses without ``--calib``), or needs scan
  times the input does not have: then the preset is *unavailable*, not negative.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.conventions import PRESETS, get_convention
from lidar_iris_eval.evaluation.ground_truth import (
    PLANAR_AXES,
    database_limits,
    ground_truth_for,
    gt_coordinates,
    revisit_queries_within,
    within_radius,
)
from lidar_iris_eval.evaluation.settings import Settings


@dataclass(frozen=True)
class Trajectory:
    """The poses a ground truth may be measured in, and the scan times.

    Attributes
    ----------
    camera, lidar : ``(N, 3)`` translations in that pose frame, or None when the
        input does not give that frame (camera poses without a calibration).
    times : ``(N,)`` scan times in seconds, or None.
    source : the sequence folder or pose file, for messages.
    sequence : the opened sequence when scans are there (for the overlap), else None.
    """

    camera: np.ndarray | None
    lidar: np.ndarray | None
    times: np.ndarray | None = None
    source: str = ""
    sequence: object | None = None

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        frame = self.camera if self.camera is not None else self.lidar
        return 0 if frame is None else len(frame)

    def has(self, frame: str) -> bool:
        """True when positions in ``frame`` (``camera`` / ``lidar``) are available."""
        return (self.camera if frame == "camera" else self.lidar) is not None

    def positions(self, frame: str) -> np.ndarray:
        """``(N, 3)`` translations in ``frame``; a LirisError when that frame is missing."""
        out = self.camera if frame == "camera" else self.lidar
        if out is None:
            need = "--calib (the Tr of calib.txt)" if frame == "lidar" else "camera poses"
            raise LirisError(self.source or "poses", f"no {frame}-frame poses; needs {need}")
        return out


def load_trajectory(sequence: Path | None, poses: Path | None = None, calib: Path | None = None,
                    reader_options: dict | None = None) -> Trajectory:
    """The :class:`Trajectory` of a sequence folder, or of a bare pose file (+ calib).

    Parameters
    ----------
    sequence : a sequence folder (any reader), or None for ``poses`` alone.
    poses, calib : a pose file and KITTI ``calib.txt`` (override the sequence's).
    reader_options : ``open_sequence`` keywords (only with a sequence).

    Returns
    -------
    Trajectory
        A sequence without camera poses has ``camera=None``.
    """
    reader_options = dict(reader_options or {})
    if sequence is None and poses is None:
        raise LirisError("liris gt", "give a SEQUENCE folder or --poses FILE")
    if sequence is not None:
        from lidar_iris_eval.io import open_sequence

        seq = open_sequence(sequence, poses=poses, calib=calib, **reader_options)
        camera = None if seq.camera_poses is None else seq.positions("camera")
        return Trajectory(camera=camera, lidar=seq.positions("lidar"),
                          times=None if seq.times is None else np.asarray(seq.times, float),
                          source=str(sequence), sequence=seq)
    if reader_options:
        from lidar_iris_eval.errors import options as option_names

        raise LirisError(option_names(reader_options), "needs a SEQUENCE, not only --poses")
    from lidar_iris_eval.io.poses import camera_to_lidar, read_calib, read_pose_file

    _, mats = read_pose_file(poses)
    lidar = None
    if calib is not None:
        lidar = camera_to_lidar(mats, read_calib(calib))[:, :3, 3]
    return Trajectory(camera=mats[:, :3, 3], lidar=lidar, source=str(poses))


# --- one convention on one trajectory -------------------------------------------------


def _describe_distance(conv: Settings) -> str:
    if conv.distance == "planar":
        axes = "".join("xyz"[a] for a in PLANAR_AXES[conv.pose_frame])
        return f"planar {axes[0]}-{axes[1]}, {conv.pose_frame} poses"
    return f"3-D, {conv.pose_frame} poses"


def applied(traj: Trajectory, conv: Settings) -> Settings:
    """``conv`` as ``liris gt`` applies it to ``traj``: a camera-frame preset on a sequence
    without camera poses measures between the LiDAR poses (``resolve_pose_frame``)."""
    if conv.pose_frame == "camera" and not traj.has("camera") and traj.sequence is not None:
        return conv.replace(pose_frame="lidar")
    return conv


def unavailable_reason(traj: Trajectory, conv: Settings) -> str | None:
    """Why ``conv`` cannot be applied to ``traj`` (rule ``frame``), or None."""
    if not traj.has(conv.pose_frame):
        return (f"frame: measures between {conv.pose_frame} poses, which the input does not "
                f"have" + (" (give --calib)" if conv.pose_frame == "lidar" else ""))
    if conv.exclude_seconds is not None and traj.times is None:
        return (f"window: a {conv.exclude_seconds:g} s window needs scan times (times.txt); "
                "the input has none")
    if conv.database_frames is not None and conv.query_start >= traj.n_frames:
        return (f"database split: queries start at frame {conv.query_start}, the sequence has "
                f"{traj.n_frames} frames")
    return None


class ConventionTruth:
    """One convention's ground truth on one trajectory, from the counting functions.

    Attributes
    ----------
    conv : the convention.
    coords : ground-truth coordinates (:func:`gt_coordinates`).
    limits : ``(N,)`` last database frame per query, -1 when not a query
        (:func:`database_limits`).
    revisit : ``(N,)`` revisit flag (:func:`revisit_queries_within`).
    """

    def __init__(self, traj: Trajectory, conv: Settings):
        self.traj = traj
        self.conv = conv
        positions = traj.positions(conv.pose_frame)
        self.coords = gt_coordinates(positions, conv.pose_frame, conv.distance)
        self.limits = database_limits(len(positions), conv, traj.times)
        self.revisit = revisit_queries_within(self.coords, self.limits, conv.radius,
                                              conv.inclusive_radius)

    def ground_truth(self):
        """The :class:`~.ground_truth.GroundTruth` ``liris eval`` would use."""
        return ground_truth_for(self.traj.positions(self.conv.pose_frame), self.conv,
                                self.traj.times, limits=self.limits)

    def distance(self, i: int, j: int) -> float:
        """The convention's pose distance between frames ``i`` and ``j`` (metres)."""
        return float(np.linalg.norm(self.coords[i] - self.coords[j]))

    def _radius_text(self, d: float, inside: bool) -> str:
        conv = self.conv
        sign = "<=" if conv.inclusive_radius else "<"
        verdict = "is" if inside else "is not"
        return f"{d:.3f} m ({_describe_distance(conv)}) {verdict} {sign} {conv.radius:g} m"

    def not_query_reason(self, q: int) -> str:
        """The rule that makes frame ``q`` no query (its database is empty)."""
        conv, n, times = self.conv, len(self.limits), self.traj.times
        if conv.database_frames is not None:
            return (f"database split: queries are frames >= {conv.query_start}; frame {q} "
                    f"is in the database range")
        if not conv.last_frame_query and q == n - 1:
            return "last frame: the last frame is never a query (Scan Context's evaluator)"
        if conv.exclude_seconds is not None:
            waited = times[q] - times[0]
            if conv.window_rule == "logg3d":
                return (f"window: queries only once {conv.exclude_seconds:g} s have passed "
                        f"since the first scan; frame {q} is at {waited:.2f} s")
            return (f"window: no scan at least {conv.exclude_seconds:g} s before frame {q} "
                    f"({waited:.2f} s after the first)")
        return f"E: frame {q} has no frame at least E = {conv.exclude} frames before it"

    def outside_database_reason(self, q: int, j: int) -> str:
        """The rule that keeps frame ``j`` out of query ``q``'s database."""
        conv, times = self.conv, self.traj.times
        if conv.database_frames is not None:
            return (f"database split: the database is frames 0..{conv.database_frames - 1}; "
                    f"frame {j} is not in it")
        if j >= q:
            return f"E: frame {j} is not earlier than the query {q}"
        if conv.exclude_seconds is not None:
            return (f"window: {times[q] - times[j]:.2f} s apart; query {q} may match frames up "
                    f"to {self.limits[q]} ({conv.exclude_seconds:g} s, {conv.window_rule} rule)")
        return f"E: {q - j} frames apart < E = {conv.exclude}"

    def pair_verdict(self, i: int, j: int) -> dict:
        """Is ``(i, j)`` a loop under this convention (the later frame as the query)?

        Returns a dict: ``positive`` (bool), ``within_radius`` (the protocol 2
        positive pair), ``distance_m``, ``rule`` (the deciding rule, or every
        rule that passed) and ``failed`` (names of the rules that failed).
        """
        conv = self.conv
        q, db = max(i, j), min(i, j)
        d = self.distance(i, j)
        near = bool(within_radius(d, conv.radius, conv.inclusive_radius))
        reasons, failed = [], []
        if self.limits[q] < 0:
            reasons.append(self.not_query_reason(q))
            failed.append(reasons[-1].split(":")[0])
        elif db > self.limits[q]:
            reasons.append(self.outside_database_reason(q, db))
            failed.append(reasons[-1].split(":")[0])
        if not near:
            reasons.append("radius: " + self._radius_text(d, False))
            failed.append("radius")
            band = conv.not_revisit_radius
            if band is not None and d <= band:
                reasons.append(f"not-revisit band: {conv.radius:g}-{band:g} m, an accepted match "
                               "here is neither a true nor a false positive")
        positive = not failed
        if positive:
            window = (f"{q - db} frames apart >= E = {conv.exclude}" if conv.exclude_seconds is None
                      and conv.database_frames is None else
                      f"frame {db} is in query {q}'s database (up to {self.limits[q]})")
            reasons = ["radius: " + self._radius_text(d, True), window]
        return {"positive": positive, "within_radius": bool(within_radius(d, conv.radius)),
                "distance_m": d, "failed": failed, "rule": "; ".join(reasons)}

    def query_verdict(self, q: int) -> dict:
        """Is frame ``q`` a revisit query, and why (its partner, or the failing rule)?"""
        conv = self.conv
        out = {"revisit_query": bool(self.revisit[q]), "partner": None, "partner_distance_m": None}
        limit = int(self.limits[q])
        if limit < 0:
            out["rule"] = self.not_query_reason(q)
            return out
        dists = np.linalg.norm(self.coords[: limit + 1] - self.coords[q], axis=1)
        nearest = int(np.argmin(dists))
        out["partner"], out["partner_distance_m"] = nearest, float(dists[nearest])
        inside = within_radius(dists[nearest], conv.radius, conv.inclusive_radius)
        if bool(inside) != out["revisit_query"]:  # the two must agree: same predicate
            raise AssertionError(f"explain disagrees with the count at frame {q}")
        sign = "<=" if conv.inclusive_radius else "<"
        if inside:
            out["rule"] = (f"revisit: nearest database frame {nearest} is {dists[nearest]:.3f} m "
                           f"away ({sign} {conv.radius:g} m, {_describe_distance(conv)}), "
                           f"{q - nearest} frames earlier")
            # the sensor never left the radius since its partners: a stop, and only the
            # window (E) makes it a revisit
            before = np.linalg.norm(self.coords[:q] - self.coords[q], axis=1)
            away = np.flatnonzero(~within_radius(before, conv.radius, conv.inclusive_radius))
            last_away = int(away[-1]) if len(away) else -1
            partners = np.flatnonzero(within_radius(dists, conv.radius, conv.inclusive_radius))
            if partners.min() > last_away:
                out["pseudo_revisit"] = True
                out["rule"] += (f"; a pseudo-revisit: the sensor stayed within {conv.radius:g} m "
                                f"since frame {last_away + 1}, so only the window "
                                f"({_window_name(conv)}) decides")
        else:
            out["rule"] = (f"radius: no database frame (0..{limit}) within {conv.radius:g} m; "
                           f"nearest is {nearest} at {dists[nearest]:.3f} m "
                           f"({_describe_distance(conv)})")
        return out


# --- --explain ---------------------------------------------------------------------------


def _check_frame(traj: Trajectory, k: int, name: str) -> None:
    if not 0 <= k < traj.n_frames:
        raise LirisError(f"--explain {name}={k}",
                         f"no such frame; the sequence has frames 0..{traj.n_frames - 1}")


def pair_overlap_values(traj: Trajectory, i: int, j: int) -> dict | None:
    """Range-image overlap both ways (``liris gt --gt overlap``'s definition), or None.

    Needs the scans and LiDAR poses of an opened sequence.
    """
    seq = traj.sequence
    if seq is None:
        return None
    from lidar_iris_eval.evaluation.overlap import (
        OverlapSpec,
        lidar_poses_of,
        overlap_matrix,
        points_of,
    )

    spec = OverlapSpec()
    poses = lidar_poses_of(seq)[[i, j]]
    matrix = overlap_matrix([points_of(seq, i), points_of(seq, j)], poses, spec)
    q, db = (0, 1) if i >= j else (1, 0)
    value = float(matrix[q, db])
    return {"overlap_i_j": float(matrix[0, 1]), "overlap_j_i": float(matrix[1, 0]),
            "overlap_positive": value >= spec.threshold,
            "overlap_rule": f"overlap(query = later frame) {value:.3f} vs >= {spec.threshold:g}"}


def explain_pair(traj: Trajectory, i: int, j: int,
                 presets: dict[str, Settings] | None = None) -> dict:
    """Everything that decides whether ``(i, j)`` is a loop, under every preset.

    Parameters
    ----------
    traj : the trajectory (:func:`load_trajectory`).
    i, j : frame indices (0-based); ``i`` is also asked as a revisit query.
    presets : name -> convention; default every preset of the conventions table.

    Returns
    -------
    dict
        ``pair`` (distances 3-D and planar in each available frame, frames
        and seconds apart, overlap when scans are there) and ``conventions``
        (one entry per preset: ``status`` positive / negative / unavailable,
        ``rule``, ``i_revisit_query`` and its ``i_rule``).
    """
    _check_frame(traj, i, "I")
    _check_frame(traj, j, "J")
    if i == j:
        raise LirisError(f"--explain {i} {j}", "give two different frames")
    presets = PRESETS if presets is None else presets
    pair: dict = {"i": i, "j": j, "frames_apart": abs(i - j)}
    for frame in ("camera", "lidar"):
        if not traj.has(frame):
            pair[f"{frame}_3d_m"] = pair[f"{frame}_planar_m"] = None
            continue
        pos = traj.positions(frame)
        for distance in ("3d", "planar"):
            coords = gt_coordinates(pos[[i, j]], frame, distance)
            pair[f"{frame}_{distance}_m"] = float(np.linalg.norm(coords[0] - coords[1]))
    pair["seconds_apart"] = (None if traj.times is None
                             else float(abs(traj.times[i] - traj.times[j])))
    overlap = pair_overlap_values(traj, i, j)
    if overlap is not None:
        pair.update(overlap)
    rows = []
    for name, conv in presets.items():
        row = {"convention": name, "radius_m": conv.radius,
               "window": (f"{conv.exclude_seconds:g}s" if conv.exclude_seconds is not None
                          else f"db 0..{conv.database_frames - 1}, q >= {conv.query_start}"
                          if conv.database_frames is not None else f"E={conv.exclude}"),
               "distance": conv.distance, "pose_frame": conv.pose_frame}
        conv = applied(traj, conv)
        row["pose_frame"] = conv.pose_frame
        why = unavailable_reason(traj, conv)
        if why is not None:
            rows.append({**row, "status": "unavailable", "rule": why, "i_revisit_query": None,
                         "i_rule": why})
            continue
        truth = ConventionTruth(traj, conv)
        verdict = truth.pair_verdict(i, j)
        query = truth.query_verdict(i)
        rows.append({**row, "status": "positive" if verdict["positive"] else "negative",
                     "decided_by": verdict["failed"] or ["all rules pass"],
                     "rule": verdict["rule"], "distance_m": verdict["distance_m"],
                     "i_revisit_query": query["revisit_query"], "i_rule": query["rule"]})
    return {"source": traj.source, "frames": traj.n_frames, "pair": pair, "conventions": rows}


# --- --diff ------------------------------------------------------------------------------


@dataclass(frozen=True)
class ConventionDiff:
    """What two conventions disagree on, on one trajectory.

    Attributes
    ----------
    a, b : the two conventions.
    counts : per convention the positive ordered pairs and revisit queries
        (what ``liris gt --convention NAME`` prints).
    pairs_only_a, pairs_only_b : ``(K, 2)`` unordered positive pairs ``(i, j)``,
        ``i < j``, that one has and the other lacks.
    queries_only_a, queries_only_b : revisit query indices one has and the other lacks.
    """

    a: ConventionTruth
    b: ConventionTruth
    counts: dict
    pairs_only_a: np.ndarray
    pairs_only_b: np.ndarray
    queries_only_a: np.ndarray
    queries_only_b: np.ndarray

    def summary(self) -> dict:
        """Counts as a JSON-ready dict; ``a_minus_b`` equals the count differences."""
        na, nb = self.a.conv.name, self.b.conv.name
        return {
            "a": na, "b": nb, **self.counts,
            "positive_ordered_pairs_only_a": 2 * len(self.pairs_only_a),
            "positive_ordered_pairs_only_b": 2 * len(self.pairs_only_b),
            "revisit_queries_only_a": int(len(self.queries_only_a)),
            "revisit_queries_only_b": int(len(self.queries_only_b)),
            "positive_ordered_pairs_a_minus_b": 2 * (len(self.pairs_only_a)
                                                     - len(self.pairs_only_b)),
            "revisit_queries_a_minus_b": int(len(self.queries_only_a) - len(self.queries_only_b)),
        }

    def deciding_rules(self, has: ConventionTruth, lacks: ConventionTruth,
                       queries: np.ndarray) -> dict[int, list[str]]:
        """Per query of ``has`` that ``lacks`` does not count: the rules that decide.

        A rule decides when giving ``lacks`` that one rule of ``has`` (the
        radius; the window: E, seconds, split, last frame; the frame and
        distance) makes the query a revisit, counted by the same functions.
        """
        groups = {"radius": ("radius", "inclusive_radius"),
                  "window": ("exclude", "exclude_seconds", "window_rule", "database_frames",
                             "query_start", "last_frame_query"),
                  "frame": ("pose_frame", "distance")}
        out: dict[int, list[str]] = {int(q): [] for q in queries.tolist()}
        if not out:
            return out
        for rule, keys in groups.items():
            values = {k: getattr(has.conv, k) for k in keys}
            if all(getattr(lacks.conv, k) == v for k, v in values.items()):
                continue
            variant = ConventionTruth(lacks.traj, lacks.conv.replace(**values))
            for q in out:
                if variant.revisit[q]:
                    out[q].append(_window_name(has.conv) if rule == "window" else rule)
        return out

    def rows(self) -> list[dict]:
        """One row per differing revisit query, then per differing unordered positive pair.

        A query row names the rules that decide (:meth:`deciding_rules`) and
        the verdict of the convention lacking it (:meth:`ConventionTruth.query_verdict`).
        """
        out = []
        for has, lacks, queries, tag in ((self.a, self.b, self.queries_only_a, "a"),
                                         (self.b, self.a, self.queries_only_b, "b")):
            deciders = self.deciding_rules(has, lacks, queries)
            for q in queries.tolist():
                mine, other = has.query_verdict(q), lacks.query_verdict(q)
                rules = deciders[q]
                why = (f"decided by {' and '.join(rules)} ({has.conv.name}'s "
                       f"{' / '.join(rules)} makes it a revisit under {lacks.conv.name}); "
                       if rules else "decided by several rules together; ") + other["rule"]
                out.append({"kind": "revisit_query", "only_in": tag,
                            "convention": has.conv.name, "i": q, "j": mine["partner"],
                            f"distance_{self.a.conv.name}_m": _distance_or_none(self.a, q,
                                                                                  mine["partner"]),
                            f"distance_{self.b.conv.name}_m": _distance_or_none(self.b, q,
                                                                                  mine["partner"]),
                            "decided_by": "+".join(rules) or "several",
                            "why_not_in_other": why})
        for has, lacks, pairs, tag in ((self.a, self.b, self.pairs_only_a, "a"),
                                       (self.b, self.a, self.pairs_only_b, "b")):
            ra = "<=" if lacks.conv.inclusive_radius else "<"
            for i, j in pairs.tolist():
                d_other = lacks.distance(i, j)
                out.append({"kind": "positive_pair", "only_in": tag,
                            "convention": has.conv.name, "i": j, "j": i, "decided_by": "radius"
                            if lacks.conv.pose_frame == has.conv.pose_frame
                            and lacks.conv.distance == has.conv.distance else "radius+frame",
                            f"distance_{self.a.conv.name}_m": self.a.distance(i, j),
                            f"distance_{self.b.conv.name}_m": self.b.distance(i, j),
                            "why_not_in_other": f"radius: {d_other:.3f} m vs {ra} "
                                                f"{lacks.conv.radius:g} m "
                                                f"({_describe_distance(lacks.conv)})"})
        return out


def _window_name(conv: Settings) -> str:
    """The name of a convention's window rule: E, window (seconds), database split."""
    if conv.database_frames is not None:
        return "database split"
    if conv.exclude_seconds is not None:
        return "window"
    return "E" if conv.last_frame_query else "E/last frame"


def _distance_or_none(truth: ConventionTruth, i: int, j: int | None) -> float | None:
    return None if j is None else truth.distance(i, j)


def _pair_set_difference(p: np.ndarray, q: np.ndarray, n: int) -> np.ndarray:
    """Rows of ``p`` (unordered pairs) not in ``q``."""
    kp = p[:, 0].astype(np.int64) * n + p[:, 1]
    kq = q[:, 0].astype(np.int64) * n + q[:, 1]
    return p[~np.isin(kp, kq)]


#: rules a ``--diff`` spec may change after the preset name (``NAME:radius=4,exclude=50``)
SPEC_KEYS = {"radius": float, "exclude": int, "distance": str, "pose_frame": str}


def preset_named(spec: str, flag: str) -> Settings:
    """The single-sequence preset of ``spec``: ``NAME`` or ``NAME:key=value,...``.

    ``key`` is one of :data:`SPEC_KEYS` (``radius``, ``exclude`` in frames,
    ``distance``, ``pose_frame``); the result is named ``spec``. Anything else
    is a LirisError naming ``flag``.
    """
    from lidar_iris_eval.evaluation.conventions import with_overrides

    name, _, rest = spec.partition(":")
    if name not in PRESETS:
        raise LirisError(f"{flag}{spec}", f"not a single-sequence convention preset; choose "
                                          f"from {', '.join(PRESETS)} (optionally "
                                          f"NAME:radius=4,exclude=50)")
    conv = get_convention(name)
    if not rest:
        return conv
    values = {}
    for item in rest.split(","):
        key, eq, text = item.partition("=")
        key = key.strip().replace("-", "_")
        if not eq or key not in SPEC_KEYS:
            raise LirisError(f"{flag}{spec}", f"expected key=value with key one of "
                                              f"{', '.join(SPEC_KEYS)}")
        try:
            values[key] = SPEC_KEYS[key](text.strip())
        except ValueError:
            raise LirisError(f"{flag}{spec}", f"bad value {text!r} for {key}") from None
    if "exclude" in values and (conv.exclude_seconds is not None
                                or conv.database_frames is not None):
        raise LirisError(f"{flag}{spec}", f"{name} has no window in frames to change")
    return with_overrides(conv, name=spec, source=f"{conv.source}; changed: {rest}", **values)


def diff_conventions(traj: Trajectory, name_a: str, name_b: str) -> ConventionDiff:
    """The positive pairs and revisit queries that ``name_a`` has and ``name_b`` lacks, and back.

    Both are presets of the conventions table; the counts are those of
    :func:`~.ground_truth.ground_truth_for`, the same as ``liris gt --convention``.
    """
    truths = []
    for flag, name in (("A", name_a), ("B", name_b)):
        conv = preset_named(name, f"--diff {flag}=")
        conv = applied(traj, conv)
        why = unavailable_reason(traj, conv)
        if why is not None:
            raise LirisError(f"--diff {flag}={name}", why)
        truths.append(ConventionTruth(traj, conv))
    a, b = truths
    ga, gb = a.ground_truth(), b.ground_truth()
    n = traj.n_frames
    counts = {f"positive_ordered_pairs_{name_a}": ga.n_positive_pairs,
              f"positive_ordered_pairs_{name_b}": gb.n_positive_pairs,
              f"revisit_queries_{name_a}": ga.n_revisits,
              f"revisit_queries_{name_b}": gb.n_revisits}
    return ConventionDiff(
        a=a, b=b, counts=counts,
        pairs_only_a=_pair_set_difference(ga.pairs, gb.pairs, n),
        pairs_only_b=_pair_set_difference(gb.pairs, ga.pairs, n),
        queries_only_a=np.flatnonzero(ga.revisit & ~gb.revisit),
        queries_only_b=np.flatnonzero(gb.revisit & ~ga.revisit))


def write_diff_csv(diff: ConventionDiff, path: Path) -> int:
    """Write :meth:`ConventionDiff.rows` atomically to ``path``; returns the row count.

    The caller checks first (:func:`~lidar_iris_eval.ownership.check_new_files`)
    that no user file is replaced without ``--overwrite``.
    """
    import csv
    import io

    from lidar_iris_eval.atomic import atomic_write

    rows = diff.rows()
    columns = ["kind", "only_in", "convention", "i", "j", "decided_by",
               f"distance_{diff.a.conv.name}_m", f"distance_{diff.b.conv.name}_m",
               "why_not_in_other"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in row.items()})
    atomic_write(path, buf.getvalue(), "--diff-csv")
    return len(rows)
