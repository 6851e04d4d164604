"""``liris datasets check SEQ``: what to look at in a sequence before trusting its numbers.

Every check reads the sequence exactly as ``liris eval`` would (the same
reader, the same pose matching) plus, where the reader's files allow, the raw
pose file, and reports a *finding* for each of:

* **scan gap** / **pose gap** – a step between consecutive scan (or pose) times
  longer than ``gap_factor`` times the median step (default 3: at 10 Hz, a
  step over 0.3 s);
* **pose rate** – the pose stream is slower than the scans (beyond
  ``rate_tolerance``, 10 %), so scans between two pose samples get
  interpolated poses; or poses matched one per scan by index while their own
  stamps disagree with the scan times by more than the matching tolerance;
* **scans without poses** – scans the reader dropped because no pose sample
  lies within the matching tolerance (and how the rest were matched);
* **stationary span** – at least ``stationary_seconds`` (2 s) of steps slower
  than ``stationary_speed`` (0.2 m/s);
* **pseudo-revisit** – a revisit query at the exclusion window E (default
  30 frames, the ``liris`` preset's 4 m) whose every database partner was
  reached *without leaving the radius*: the sensor waited (a traffic light,
  a stop), it did not come back. They are what separates KITTI 00's 816
  revisit queries at E = 30 from its 791 at E = 50;
* **speed jump** / **yaw-rate jump** – a step faster than the platform's
  limit (:data:`PLATFORMS`): a ground-truth jump, not motion;
* **duplicate stamp** – two scans (or two poses) with the same time, or
  times going backwards.

A clean sequence has no finding; the summary also gives the scan and pose
rates, the largest steps and the matching method.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError


@dataclass(frozen=True)
class CheckLimits:
    """The thresholds of ``liris datasets check`` (every one named in its output).

    Attributes
    ----------
    platform : name of the platform the speed and yaw-rate limits are for.
    max_speed : m/s; a faster step between two poses is a ground-truth jump.
    max_yaw_rate : deg/s; a faster heading change is a ground-truth jump.
    gap_factor : a time step longer than this times the median step is a gap.
    rate_tolerance : relative; a pose rate this much below the scan rate is a mismatch.
    stationary_speed : m/s; slower steps are "not moving".
    stationary_seconds : a run of not-moving steps this long is a stationary span.
    exclude : E (frames) for the pseudo-revisit count, with the ``liris`` preset's radius.
    """

    platform: str = "car"
    max_speed: float = 40.0
    max_yaw_rate: float = 120.0
    gap_factor: float = 3.0
    rate_tolerance: float = 0.1
    stationary_speed: float = 0.2
    stationary_seconds: float = 2.0
    exclude: int = 30


#: platform limits: a car (KITTI, MulRan, Boreas, nuScenes, Oxford: 144 km/h, 120 deg/s),
#: a ground robot (NCLT's Segway: 5 m/s, 180 deg/s), a hand-held or backpack sensor
#: (Newer College, Wild-Places, HKU Livox: 5 m/s, 360 deg/s)
PLATFORMS: dict[str, CheckLimits] = {
    "car": CheckLimits(platform="car", max_speed=40.0, max_yaw_rate=120.0),
    "robot": CheckLimits(platform="robot", max_speed=5.0, max_yaw_rate=180.0),
    "handheld": CheckLimits(platform="handheld", max_speed=5.0, max_yaw_rate=360.0),
}


def limits_for(platform: str = "car", **overrides) -> CheckLimits:
    """The limits of ``platform`` with ``overrides`` (None values ignored) on top."""
    if platform not in PLATFORMS:
        raise LirisError(f"--platform {platform}", f"choose from {', '.join(PLATFORMS)}")
    given = {k: v for k, v in overrides.items() if v is not None}
    for key, value in given.items():
        if key != "exclude" and not (isinstance(value, (int, float)) and 0 < value < np.inf):
            raise LirisError(f"--{key.replace('_', '-')} {value}", "must be a positive number")
    if given.get("exclude") is not None and given["exclude"] < 1:
        raise LirisError(f"--exclude {given['exclude']}", "must be at least 1 frame")
    return replace(PLATFORMS[platform], **given)


@dataclass(frozen=True)
class TimingInput:
    """What the checks read: the sequence as liris uses it, and the raw pose stream.

    Attributes
    ----------
    times : ``(N,)`` scan times (s) of the scans liris uses, or None.
    poses : ``(N, 4, 4)`` LiDAR-frame poses of those scans (z up).
    ground_truth_positions : ``(N, 3)`` translations ground truth uses (camera
        frame when there is one), for the pseudo-revisit count.
    pose_times : ``(M,)`` stamps of the raw pose file, or None (one pose per line).
    n_scans_listed : scan files found before matching, or None when unknown.
    matched_by : ``"index"``, ``"time"`` or ``"reader"`` (how scans got their poses;
        ``"reader"``: a dataset reader matched them, its raw pose stamps are not read here).
    tolerance : seconds, the time-matching tolerance.
    assumed_rate : Hz used for missing scan times (None: time checks are skipped).
    source : the sequence, for messages.
    """

    times: np.ndarray | None
    poses: np.ndarray
    ground_truth_positions: np.ndarray
    pose_times: np.ndarray | None = None
    n_scans_listed: int | None = None
    matched_by: str = "index"
    tolerance: float = 0.1
    assumed_rate: float | None = None
    source: str = ""


@dataclass
class CheckReport:
    """Findings (faults) and a summary (rates, largest steps, matching).

    ``limits`` are the thresholds used; ``pseudo`` (``(N,)`` bool), ``speed`` and
    ``dt`` (``(N - 1,)``) are kept for the figure (None when not computed).
    """

    summary: dict
    findings: list[dict] = field(default_factory=list)
    limits: CheckLimits | None = None
    pseudo: np.ndarray | None = None
    speed: np.ndarray | None = None
    dt: np.ndarray | None = None

    def add(self, check: str, detail: str, frames: tuple[int, int] | None = None,
            value: float | None = None) -> None:
        """Record one finding of ``check`` (frames: first and last frame involved)."""
        self.findings.append({"check": check, "frames": None if frames is None else list(frames),
                              "value": value, "detail": detail})

    def counts(self) -> dict[str, int]:
        """Findings per check, every check listed (0 when clean)."""
        out = dict.fromkeys(CHECKS, 0)
        for f in self.findings:
            out[f["check"]] += 1
        return out

    def to_dict(self) -> dict:
        """JSON-ready: summary, per-check counts, findings."""
        return {**self.summary, "clean": not self.findings, "checks": self.counts(),
                "findings": self.findings}


CHECKS = ("scan gap", "pose gap", "pose rate", "scans without poses", "stationary span",
          "pseudo-revisit", "speed jump", "yaw-rate jump", "duplicate stamp")


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``(start, stop)`` of the runs of True in ``mask`` (stop excluded)."""
    mask = np.asarray(mask, dtype=bool)
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(),
                    strict=True))


def _median_step(times: np.ndarray) -> float | None:
    steps = np.diff(times)
    steps = steps[steps > 0]
    return float(np.median(steps)) if len(steps) else None


def _check_stamps(report: CheckReport, times: np.ndarray, what: str, limits: CheckLimits,
                  gap_check: str) -> float | None:
    """Gaps and duplicate / backward stamps of one stream; returns its median step."""
    steps = np.diff(times)
    for k in np.flatnonzero(steps <= 0).tolist():
        kind = "the same time" if steps[k] == 0 else "a time going backwards"
        report.add("duplicate stamp", f"{what} {k} and {k + 1} have {kind} "
                                      f"({times[k]:.6f} s, {times[k + 1]:.6f} s)",
                   (k, k + 1), float(steps[k]))
    median = _median_step(times)
    if median is None:
        return None
    for k in np.flatnonzero(steps > limits.gap_factor * median).tolist():
        report.add(gap_check, f"{steps[k]:.3f} s between {what} {k} and {k + 1} "
                              f"(median step {median:.3f} s, gap > {limits.gap_factor:g}x)",
                   (k, k + 1), float(steps[k]))
    return median


def pseudo_revisits(positions: np.ndarray, exclude: int | str = 30
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Revisit queries at E = ``exclude`` under the ``liris`` preset, and the pseudo ones.

    ``exclude`` is frames or a named window (``"paper"``, ``"reference"``),
    merged into the preset by :meth:`Settings.from_options`, the one parse of
    a window, so a bad value is the same one-line error as on the command line.

    A revisit query ``i`` is *pseudo* when none of its database partners
    (``j <= i - E`` within the radius) lies before the last frame ``k < i``
    that was at least the radius away from ``i``: the sensor never left.

    Returns
    -------
    ``(revisit (N,) bool, pseudo (N,) bool)``, both from
    :func:`~lidar_iris_eval.evaluation.ground_truth.revisit_queries_within`.
    """
    from scipy.spatial import cKDTree

    from lidar_iris_eval.evaluation.conventions import PRESETS
    from lidar_iris_eval.evaluation.ground_truth import (
        database_limits,
        gt_coordinates,
        revisit_queries_within,
    )
    from lidar_iris_eval.evaluation.settings import Settings

    conv = Settings.from_options(PRESETS["liris"], exclude=exclude)
    coords = gt_coordinates(positions, "camera", conv.distance)  # 3-D: the frame only names axes
    n = len(coords)
    limits = database_limits(n, conv)
    revisit = revisit_queries_within(coords, limits, conv.radius, conv.inclusive_radius)
    # last_away[i]: the last k < i at least the radius away (-1: never left since the start)
    last_away = np.full(n, -1, dtype=np.int64)
    tree = cKDTree(coords)
    for i in np.flatnonzero(revisit).tolist():
        near = np.asarray(tree.query_ball_point(coords[i], conv.radius), dtype=np.int64)
        near = near[np.linalg.norm(coords[near] - coords[i], axis=1) < conv.radius]
        inside = np.zeros(i + 1, dtype=bool)
        inside[near[near <= i]] = True
        away = np.flatnonzero(~inside)
        last_away[i] = int(away[-1]) if len(away) else -1
    genuine = revisit_queries_within(coords, np.minimum(limits, last_away - 1), conv.radius,
                                     conv.inclusive_radius)
    return revisit, revisit & ~genuine


def check_timing(data: TimingInput, limits: CheckLimits = PLATFORMS["car"]) -> CheckReport:
    """Run every check on ``data`` (see the module docstring)."""
    poses = np.asarray(data.poses, dtype=np.float64)
    n = len(poses)
    times = data.times
    time_source = "scan times"
    if times is None and data.assumed_rate is not None:
        times = np.arange(n) / float(data.assumed_rate)
        time_source = f"assumed {data.assumed_rate:g} Hz (no scan times)"
    summary: dict = {"source": data.source, "scans": n, "times": time_source if times is not None
                     else "none (time checks skipped; give --rate HZ)",
                     "platform": limits.platform, "max_speed_m_s": limits.max_speed,
                     "max_yaw_rate_deg_s": limits.max_yaw_rate,
                     "gap_factor": limits.gap_factor,
                     "stationary": f"< {limits.stationary_speed:g} m/s for >= "
                                   f"{limits.stationary_seconds:g} s",
                     "pseudo_revisit_exclude": limits.exclude}
    report = CheckReport(summary, limits=limits)
    scan_step = None
    if times is not None:
        times = np.asarray(times, dtype=np.float64)
        if not np.all(np.isfinite(times)):
            raise LirisError(data.source or "times", "scan times must be finite numbers")
        scan_step = _check_stamps(report, times, "scans", limits, "scan gap")
    summary["scan_rate_hz"] = None if scan_step is None else 1.0 / scan_step
    _check_poses_stream(report, data, limits, scan_step)
    if times is not None and n > 1:
        _check_motion(report, poses, times, limits)
    revisit, pseudo = pseudo_revisits(data.ground_truth_positions, limits.exclude)
    summary["revisit_queries_at_exclude"] = int(np.count_nonzero(revisit))
    summary["pseudo_revisit_queries"] = int(np.count_nonzero(pseudo))
    for start, stop in _runs(pseudo):
        report.add("pseudo-revisit", f"{stop - start} revisit queries at E = {limits.exclude} "
                                     f"(frames {start}..{stop - 1}) whose partners were reached "
                                     "without leaving 4 m (a stop, not a loop)",
                   (start, stop - 1), float(stop - start))
    report.pseudo = pseudo  # for the figure
    return report


def _check_poses_stream(report: CheckReport, data: TimingInput, limits: CheckLimits,
                        scan_step: float | None) -> None:
    """Pose stamps: gaps, duplicates, rate against the scans, matching, dropped scans."""
    summary = report.summary
    summary["matched_by"] = (
        "index (one pose line per scan)" if data.matched_by == "index" else
        "the dataset reader (by time or by index: docs/datasets.md, Time matching)"
        if data.matched_by == "reader" else
        f"time (linear / slerp interpolation; scans with no pose sample within "
        f"{data.tolerance:g} s are dropped)")
    summary["scans_listed"] = data.n_scans_listed
    if data.n_scans_listed is not None and data.n_scans_listed > len(data.poses):
        dropped = data.n_scans_listed - len(data.poses)
        report.add("scans without poses", f"{dropped} of {data.n_scans_listed} scans have no pose "
                                          f"within {data.tolerance:g} s and are dropped "
                                          f"(matched by {data.matched_by})",
                   None, float(dropped))
    if data.pose_times is None:
        summary["pose_rate_hz"] = None
        summary["pose_stamps"] = "none (one pose per scan)"
        return
    pose_times = np.asarray(data.pose_times, dtype=np.float64)
    summary["pose_stamps"] = len(pose_times)
    pose_step = _check_stamps(report, pose_times, "poses", limits, "pose gap")
    summary["pose_rate_hz"] = None if pose_step is None else 1.0 / pose_step
    if pose_step is None or scan_step is None:
        return
    pose_rate, scan_rate = 1.0 / pose_step, 1.0 / scan_step
    if pose_rate < scan_rate * (1.0 - limits.rate_tolerance):
        report.add("pose rate", f"poses at {pose_rate:.2f} Hz, scans at {scan_rate:.2f} Hz: "
                                "scans between pose samples get interpolated poses",
                   None, pose_rate / scan_rate)
    elif data.matched_by == "index" and data.times is not None \
            and len(pose_times) == len(data.times):
        off = float(np.max(np.abs(pose_times - np.asarray(data.times))))
        if off > data.tolerance:
            report.add("pose rate", f"poses are matched one per scan by index, but their stamps "
                                    f"differ from the scan times by up to {off:.3f} s "
                                    f"(poses {pose_rate:.2f} Hz, scans {scan_rate:.2f} Hz)",
                       None, off)


def _yaw(poses: np.ndarray) -> np.ndarray:
    return np.arctan2(poses[:, 1, 0], poses[:, 0, 0])


def _check_motion(report: CheckReport, poses: np.ndarray, times: np.ndarray,
                  limits: CheckLimits) -> None:
    """Speed and yaw-rate jumps, stationary spans."""
    dt = np.diff(times)
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    turn = np.degrees(np.abs(np.angle(np.exp(1j * np.diff(_yaw(poses))))))
    timed = dt > 0
    speed = np.where(timed, step / np.where(timed, dt, 1.0), np.nan)
    yaw_rate = np.where(timed, turn / np.where(timed, dt, 1.0), np.nan)
    summary = report.summary
    summary["speed_max_m_s"] = float(np.nanmax(speed)) if timed.any() else None
    summary["yaw_rate_max_deg_s"] = float(np.nanmax(yaw_rate)) if timed.any() else None
    for check, value, limit, unit, moved, word in (
            ("speed jump", speed, limits.max_speed, "m/s", step, "m"),
            ("yaw-rate jump", yaw_rate, limits.max_yaw_rate, "deg/s", turn, "deg")):
        for start, stop in _runs(timed & (value > limit)):
            peak = float(np.max(value[start:stop]))
            if stop - start == 1:
                detail = (f"{moved[start]:.2f} {word} in {dt[start]:.3f} s between frames "
                          f"{start} and {start + 1} ({peak:.1f} {unit} > {limit:g} {unit}, "
                          f"{limits.platform})")
            else:
                detail = (f"{stop - start} consecutive steps above {limit:g} {unit} "
                          f"({limits.platform}) between frames {start} and {stop}, up to "
                          f"{peak:.1f} {unit}")
            report.add(check, detail, (start, stop), peak)
    # untimed steps (duplicate stamps) count as still when the pose does not move
    still = np.where(timed, speed < limits.stationary_speed, step < 1e-6)
    spans = 0
    for start, stop in _runs(still):
        seconds = float(times[stop] - times[start])
        if seconds >= limits.stationary_seconds:
            spans += 1
            moved = float(np.linalg.norm(poses[stop, :3, 3] - poses[start, :3, 3]))
            report.add("stationary span", f"frames {start}..{stop}: {seconds:.1f} s, "
                                          f"{moved:.2f} m moved", (start, stop), seconds)
    summary["stationary_spans"] = spans
    report.speed = speed
    report.dt = dt


# --- reading a sequence ----------------------------------------------------------------


def timing_input(sequence: Path | None, poses: Path | None = None, calib: Path | None = None,
                 reader_options: dict | None = None, rate: float | None = None) -> TimingInput:
    """Gather a :class:`TimingInput` from a sequence folder (any reader) or a bare pose file.

    The sequence is opened as ``liris eval`` opens it; the raw pose file (for
    its stamps) and the scan listing (for dropped scans) are read where the
    reader's layout is a folder of scans with a pose file (KITTI, plain folders).
    """
    from lidar_iris_eval.io.poses import read_pose_file
    from lidar_iris_eval.io.timematch import DEFAULT_TOLERANCE

    opts = dict(reader_options or {})
    if rate is not None and not (0 < rate < np.inf):
        raise LirisError(f"--rate {rate}", "must be a positive number of Hz")
    if sequence is None:
        if poses is None:
            raise LirisError("liris datasets check", "give a SEQUENCE folder or --poses FILE")
        if opts:
            from lidar_iris_eval.errors import options as option_names

            raise LirisError(option_names(opts), "needs a SEQUENCE, not only --poses")
        pose_times, mats = read_pose_file(poses)
        return TimingInput(times=pose_times, poses=_z_up(mats, calib),
                           ground_truth_positions=mats[:, :3, 3], pose_times=None,
                           assumed_rate=rate, source=str(poses))
    from lidar_iris_eval.io import open_sequence

    seq = open_sequence(sequence, poses=poses, calib=calib, **opts)
    raw_path = poses if poses is not None else _pose_file_of(Path(sequence), seq)
    pose_times, n_raw = None, None
    if raw_path is not None:
        try:
            pose_times, raw = read_pose_file(raw_path, opts.get("pose_format", "auto"))
            n_raw = len(raw)
        except LirisError:
            pose_times = None
    listed = _listed_scans(seq) if not {"frames", "every", "min_distance"} & set(opts) else None
    matched_by = "time" if (pose_times is not None and listed is not None and n_raw != listed) \
        else "index"
    unmatched = getattr(seq, "unmatched", None)
    if raw_path is None and unmatched is not None:  # a dataset reader: it matched the poses
        matched_by = "reader"
        listed = len(seq) + int(unmatched) if listed is None or listed < len(seq) + unmatched \
            else listed
    gt = seq.positions("camera" if seq.camera_poses is not None else "lidar")
    return TimingInput(times=None if seq.times is None else np.asarray(seq.times, float),
                       poses=np.asarray(seq.poses, float), ground_truth_positions=gt,
                       pose_times=pose_times, n_scans_listed=listed, matched_by=matched_by,
                       tolerance=float(opts.get("tolerance", DEFAULT_TOLERANCE)),
                       assumed_rate=rate, source=str(sequence))


def _z_up(camera_poses: np.ndarray, calib: Path | None) -> np.ndarray:
    """z-up poses from KITTI camera poses: ``inv(Tr)·T·Tr`` with a calib, else the
    camera axes turned to x forward, y left, z up (enough for speeds and yaw rates)."""
    if calib is None:
        axes = np.eye(4)
        axes[:3, :3] = [[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]
        return axes @ camera_poses @ axes.T
    from lidar_iris_eval.io.poses import camera_to_lidar, read_calib

    return camera_to_lidar(camera_poses, read_calib(calib))


def _pose_file_of(sequence: Path, seq) -> Path | None:
    """The pose file a KITTI layout or plain scan folder reads (None for other readers)."""
    from lidar_iris_eval.io.folder import find_pose_file
    from lidar_iris_eval.io.kitti import find_kitti_poses, is_kitti_layout

    if is_kitti_layout(sequence):
        root = sequence.parent if sequence.name == "velodyne" else sequence
        return find_kitti_poses(root)
    try:
        return find_pose_file(sequence) if sequence.is_dir() else None
    except LirisError:
        return None


def _listed_scans(seq) -> int | None:
    """Scan files in the folder the sequence's scans come from (None if not one folder)."""
    from lidar_iris_eval.io.sequence import list_scans

    paths = getattr(seq, "scan_paths", None) or []
    parents = {Path(p).parent for p in paths if isinstance(p, Path)}
    if len(parents) != 1:
        return None
    try:
        return len(list_scans(parents.pop()))
    except LirisError:
        return None
