"""Pairing scans with poses by time, and choosing keyframes.

Recorded data rarely has one pose per scan: odometry may run at 50 Hz while
the LiDAR turns at 10 Hz, and a TUM trajectory may start later than the
recording. Each scan gets the pose *at its timestamp*, interpolated linearly in
translation and by slerp in rotation between the two poses around it. A scan
whose nearest pose sample is further away than ``tolerance`` seconds gets none
(interpolating across a gap in the odometry would invent a pose); it is
dropped, and the caller warns with the count.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, warn

#: default matching tolerance: one revolution of a 10 Hz spinning LiDAR
DEFAULT_TOLERANCE = 0.1

#: integer file-name stamps by digit count -> seconds per unit (s, ms, µs, ns)
STAMP_DIGITS = {10: 1.0, 13: 1e-3, 16: 1e-6, 19: 1e-9}
DECIMAL_STAMP = re.compile(r"^\d+\.\d+$")


def interpolate_poses(
    pose_times: np.ndarray,
    poses: np.ndarray,
    query_times: np.ndarray,
    tolerance: float = DEFAULT_TOLERANCE,
) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query_times``, interpolated from timestamped ``poses``.

    Parameters
    ----------
    pose_times : ``(M,)`` seconds; sorted here (duplicates keep the first pose).
    poses : ``(M, 4, 4)`` rigid transforms.
    query_times : ``(N,)`` seconds.
    tolerance : a query is valid when a pose sample lies within this many
        seconds of it; outside the pose time range the end pose is used (no
        extrapolation), which the same tolerance bounds.

    Returns
    -------
    ``(poses (N, 4, 4), valid (N,) bool)``; rows of invalid queries hold the
    nearest pose and must not be used.

    A query that falls exactly on a pose sample gets that pose unchanged (the
    relative rotation is scaled by exactly zero), so re-timing a trajectory on
    its own stamps is lossless.
    """
    if tolerance < 0:
        raise LirisError(f"--tolerance {tolerance}", "tolerance must be non-negative")
    pose_times = np.asarray(pose_times, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    query_times = np.asarray(query_times, dtype=np.float64)
    if len(pose_times) == 0:
        return np.tile(np.eye(4), (len(query_times), 1, 1)), np.zeros(len(query_times), bool)
    pose_times, first = np.unique(pose_times, return_index=True)
    poses = poses[first]
    last = len(pose_times) - 1
    i0 = np.clip(np.searchsorted(pose_times, query_times, side="right") - 1, 0, last)
    i1 = np.minimum(i0 + 1, last)
    t0, t1 = pose_times[i0], pose_times[i1]
    gap = np.minimum(np.abs(query_times - t0), np.abs(t1 - query_times))
    valid = gap <= tolerance
    span = np.where(i1 > i0, t1 - t0, 1.0)
    alpha = np.clip(np.where(i1 > i0, (query_times - t0) / span, 0.0), 0.0, 1.0)
    out = np.tile(np.eye(4), (len(query_times), 1, 1))
    out[:, :3, 3] = (1 - alpha)[:, None] * poses[i0, :3, 3] + alpha[:, None] * poses[i1, :3, 3]
    out[:, :3, :3] = slerp_matrices(poses[i0, :3, :3], poses[i1, :3, :3], alpha)
    return out, valid


def slerp_matrices(r0: np.ndarray, r1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Rotations ``r0 · exp(alpha · log(r0ᵀ r1))``: slerp along the shortest arc.

    Written on the relative rotation so that ``alpha == 0`` returns ``r0``
    bit for bit (no round trip through quaternions).
    """
    relative = np.einsum("nji,njk->nik", r0, r1)
    from scipy.spatial.transform import Rotation  # deferred: io.datasets imports this at start

    rotvec = Rotation.from_matrix(relative).as_rotvec()
    step = Rotation.from_rotvec(alpha[:, None] * rotvec).as_matrix()
    return r0 @ step


def match_poses(
    scan_times: np.ndarray,
    pose_times: np.ndarray,
    poses: np.ndarray,
    tolerance: float,
    source: str | Path,
) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the scans that get a pose, and those poses.

    Scans without a pose within ``tolerance`` are dropped with a warning that
    counts them; if none is left, that is an error naming ``source``.
    """
    matched, valid = interpolate_poses(pose_times, poses, scan_times, tolerance)
    keep = np.flatnonzero(valid)
    n_drop = len(scan_times) - len(keep)
    if len(keep) == 0:
        raise LirisError(
            source,
            f"no scan has a pose within {tolerance} s; scan times "
            f"[{_span(scan_times)}] vs pose times [{_span(pose_times)}] (check clocks/--tolerance)",
        )
    if n_drop:
        total = len(scan_times)
        warn(source, f"dropped {n_drop} of {total} scans with no pose within {tolerance} s")
    return keep, matched[keep]


def _span(times: np.ndarray) -> str:
    if len(times) == 0:
        return "none"
    return f"{np.min(times):.3f} .. {np.max(times):.3f}"


def select_keyframes(
    positions: np.ndarray, every: int = 1, min_distance: float = 0.0
) -> np.ndarray:
    """Indices of the keyframes to keep, in order.

    ``min_distance`` keeps the first scan, then each scan at least that many
    metres (3-D) from the last kept one, so a parked vehicle adds no frames.
    ``every`` then keeps every N-th of those. Both default to keeping all.
    """
    if int(every) != every or every < 1:
        raise LirisError(f"--every {every}", "must be a whole number of scans, at least 1")
    if not np.isfinite(min_distance) or min_distance < 0:
        raise LirisError(f"--min-distance {min_distance}", "must be a non-negative distance")
    positions = np.asarray(positions, dtype=np.float64)
    keep = np.arange(len(positions))
    if min_distance > 0 and len(positions):
        keep = _distance_keyframes(positions, min_distance)
    return keep[:: int(every)]


def _distance_keyframes(positions: np.ndarray, min_distance: float) -> np.ndarray:
    # Sequential by nature (each choice depends on the previous keyframe); the
    # loop is over frames, and each step jumps straight to the next far-enough
    # frame with a vectorised search over a bounded window.
    kept = [0]
    current = 0
    n = len(positions)
    window = 256
    while current < n - 1:
        stop = min(n, current + 1 + window)
        dist = np.linalg.norm(positions[current + 1 : stop] - positions[current], axis=1)
        far = np.flatnonzero(dist >= min_distance)
        if far.size:
            current = current + 1 + int(far[0])
            kept.append(current)
        elif stop == n:
            break
        else:
            window *= 2
            continue
        window = 256
    return np.asarray(kept, dtype=np.int64)


def stamps_from_names(paths: list[Path]) -> np.ndarray | None:
    """Seconds encoded in scan file names, or None if the names are not stamps.

    Recognised: ``1565.123456`` (decimal seconds) and integer stamps of 10,
    13, 16 or 19 digits (s, ms, µs, ns), as written by ROS tools such as
    ``pcl_ros``'s ``bag_to_pcd``. Frame numbers such as ``000042`` are not
    stamps. All names must agree on one convention.
    """
    stems = [p.stem for p in paths]
    if not stems:
        return None
    if all(DECIMAL_STAMP.match(s) for s in stems):
        return np.array([float(s) for s in stems])
    lengths = {len(s) for s in stems}
    if len(lengths) == 1 and all(s.isdigit() for s in stems):
        unit = STAMP_DIGITS.get(lengths.pop())
        if unit is not None:
            ints = np.array([int(s) for s in stems], dtype=np.int64)
            per_second = round(1 / unit)
            return (ints // per_second) + (ints % per_second) * unit
    return None
