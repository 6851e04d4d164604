"""A plain folder of scans (``.pcd``, ``.bin`` or ``.npy``) with a pose file.

Typical sources: ``pcl_ros bag_to_pcd`` output, a SLAM system's keyframe
dump, or KITTI-style scans without the KITTI folder layout.

Pose file discovery (first match wins; ``poses=`` overrides it):

1. ``poses.txt``, ``poses_tum.txt``, or a single ``*.tum`` file in the scan folder;
2. the same names in its parent folder.

The format (KITTI 3×4 rows or TUM ``t x y z qx qy qz qw``) is detected from
the first line unless ``pose_format`` says. KITTI pose files are camera-frame
by convention, so unless ``lidar_frame=True`` declares the poses to be those
of the LiDAR, a ``calib.txt`` with ``Tr`` is needed (``calib=``, or found in
the folder or its parent) to form ``inv(Tr)·T·Tr``.

Scan times come from ``times=`` / ``times.txt`` (folder or parent), else from
file names that are stamps (``1565012345.123456.pcd``, 19-digit ns …). When
the pose and scan counts differ, timestamped (TUM) poses are matched to the
scan times by interpolation; otherwise the counts must be equal.

Per-point labels (SemanticKITTI ``.label``, one per scan, same file stem) are
read from a ``labels/`` folder inside the scan folder when it exists.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, option
from lidar_iris_eval.errors import options as option_names
from lidar_iris_eval.io.poses import camera_to_lidar, read_calib, read_pose_file
from lidar_iris_eval.io.sequence import (
    Sequence,
    check_counts,
    find_labels,
    list_scans,
    read_times,
)
from lidar_iris_eval.io.timematch import (
    DEFAULT_TOLERANCE,
    match_poses,
    select_keyframes,
    stamps_from_names,
)

POSE_FILE_NAMES = ("poses.txt", "poses_tum.txt")
POSE_FILE_GLOB = "*.tum"
TIMES_FILE_NAME = "times.txt"
CALIB_FILE_NAME = "calib.txt"


def open_folder(
    path: str | Path,
    poses: str | Path | None = None,
    calib: str | Path | None = None,
    pose_format: str = "auto",
    lidar_frame: bool = False,
    times: str | Path | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
    every: int = 1,
    min_distance: float = 0.0,
    **opts,
) -> Sequence:
    """Open a folder of scans lazily, with LiDAR-frame poses.

    Parameters
    ----------
    path : the folder holding the scan files (one format per folder).
    poses : pose file; found as described in the module docstring if None.
    calib : KITTI ``calib.txt`` with ``Tr``, for camera-frame poses.
    pose_format : ``"auto"``, ``"kitti"`` or ``"tum"``.
    lidar_frame : the poses are already LiDAR poses (no ``Tr`` applied).
    times : a file with one scan time (seconds) per line.
    tolerance : seconds; a scan without a pose this close is dropped (time matching only).
    every, min_distance : keyframe selection, see :func:`select_keyframes`.
    """
    folder = Path(path)
    if opts:
        raise LirisError(folder, f"{option_names(opts)}: not used for a folder of scans")
    scan_paths = list_scans(folder)
    frame_ids = None
    scan_times = _read_times(Path(times), scan_paths, folder) if times else None
    if scan_times is None and (found := _find_first(folder, [TIMES_FILE_NAME])) is not None:
        scan_times = _read_times(found, scan_paths, folder)
    if scan_times is None and (stamps := stamps_from_names(scan_paths)) is not None:
        order = np.argsort(stamps, kind="stable")
        scan_paths = [scan_paths[i] for i in order]
        scan_times = stamps[order]
        frame_ids = np.arange(len(scan_paths))

    pose_path = Path(poses) if poses is not None else find_pose_file(folder)
    pose_times, raw_poses = read_pose_file(pose_path, pose_format)
    keep = np.arange(len(scan_paths))
    if len(raw_poses) != len(scan_paths):
        if pose_times is None or scan_times is None:
            hint = (
                " (poses have no timestamps)" if pose_times is None
                else " (no times.txt and file names are not stamps, so scans cannot be timed)"
            )
            check_counts(scan_paths, len(raw_poses), folder, f"{pose_path}{hint}")
        keep, raw_poses = match_poses(scan_times, pose_times, raw_poses, tolerance, pose_path)

    tr = _calib(folder, calib, required=not lidar_frame, pose_path=pose_path)
    if lidar_frame:
        lidar_poses = raw_poses
        camera_poses = None if tr is None else tr @ raw_poses @ np.linalg.inv(tr)
    else:
        lidar_poses = camera_to_lidar(raw_poses, tr)
        camera_poses = raw_poses

    chosen = select_keyframes(lidar_poses[:, :3, 3], every, min_distance)
    keep = keep[chosen]
    kept_paths = [scan_paths[i] for i in keep]
    labels_dir = folder / "labels"
    return Sequence(
        name=folder.name,
        path=folder,
        scan_paths=kept_paths,
        poses=lidar_poses[chosen],
        camera_poses=None if camera_poses is None else camera_poses[chosen],
        times=None if scan_times is None else scan_times[keep],
        calib=tr,
        frame_ids=_frame_ids(scan_paths, keep) if frame_ids is None else frame_ids[keep],
        label_paths=find_labels(labels_dir, kept_paths),
        labels_dir=labels_dir,
    )


def find_pose_file(folder: Path) -> Path:
    """The pose file for a scan folder (see the module docstring for the order)."""
    for place in (folder, folder.parent):
        for name in POSE_FILE_NAMES:
            if (place / name).is_file():
                return place / name
        tum = sorted(place.glob(POSE_FILE_GLOB))
        if len(tum) > 1:
            names = [p.name for p in tum]
            raise LirisError(place, f"several {POSE_FILE_GLOB} files {names}; choose with --poses")
        if tum:
            return tum[0]
    raise LirisError(
        folder,
        f"no pose file: looked for {', '.join(POSE_FILE_NAMES)} or {POSE_FILE_GLOB} here and in "
        f"{folder.parent}; give one with --poses",
    )


def _find_first(folder: Path, names: list[str]) -> Path | None:
    for place in (folder, folder.parent):
        for name in names:
            if (place / name).is_file():
                return place / name
    return None


def _calib(folder: Path, calib: str | Path | None, required: bool, pose_path: Path):
    """``Tr`` from the given or found ``calib.txt``; None if absent and not required."""
    calib_path = Path(calib) if calib is not None else _find_first(folder, [CALIB_FILE_NAME])
    if calib_path is None:
        if required:
            raise LirisError(
                pose_path,
                "poses are taken as camera-frame (KITTI convention) and need a calib.txt with Tr "
                f"to convert them (give {option('calib')}, or put calib.txt beside the scans); "
                "if they are already LiDAR poses, say so with " + option("lidar_frame", True),
            )
        return None
    return read_calib(calib_path)


def _read_times(path: Path, scan_paths: list[Path], folder: Path) -> np.ndarray:
    values = read_times(path)
    check_counts(scan_paths, len(values), folder, path, "times")
    return values


def _frame_ids(paths: list[Path], keep: np.ndarray) -> np.ndarray:
    """Numeric file names are frame ids (``000042.pcd``); otherwise the listing index."""
    return np.array([int(paths[i].stem) if paths[i].stem.isdigit() else int(i) for i in keep])
