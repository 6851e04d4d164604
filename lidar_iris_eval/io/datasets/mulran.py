"""MulRan: ``<Seq>/Ouster/<ns>.bin`` scans and ``<Seq>/global_pose.csv`` base-frame poses.

Scans are KITTI-style float32 × 4 (x, y, z, intensity) in the Ouster OS1-64
frame. ``global_pose.csv`` has a row per pose (ns stamp, then a row-major
3×4 matrix) of the *vehicle base*, at a higher rate than the scans: each scan
gets the pose at its stamp (interpolated between the two around it, within
:data:`TOLERANCE`), and the LiDAR pose is ``T_base · T_base_ouster`` with the
extrinsic of MulRan's ``calib_base2ouster.txt`` (as in kiss-icp's loader).
Some MulRan scans are broken (fewer than 64 × 1024 points); they are read as
they are.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.datasets.base import (
    build,
    check_options,
    list_files,
    match_scans,
    ns_to_seconds,
    pick,
    read_stamp_column,
    read_table,
    rpy_zyx,
    se3,
    stem_stamps,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_dir, has_file
from lidar_iris_eval.io.scans import read_kitti_bin
from lidar_iris_eval.io.sequence import Sequence

#: base -> Ouster: translation (m) and roll, pitch, yaw (degrees), calib_base2ouster.txt
BASE_TO_OUSTER_T = (1.7042, -0.021, 1.8047)
BASE_TO_OUSTER_RPY_DEG = (0.0001, 0.0003, 179.6654)
#: seconds between a scan stamp and the nearest pose sample (poses come at about 100 Hz)
TOLERANCE = 0.1
POSE_FILE = "global_pose.csv"


def base_to_ouster() -> np.ndarray:
    """``T_base_ouster``: maps Ouster-frame points into the vehicle base frame."""
    roll, pitch, yaw = np.radians(BASE_TO_OUSTER_RPY_DEG)
    return se3(rpy_zyx(roll, pitch, yaw)[0], BASE_TO_OUSTER_T)


def read_global_pose(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps ns (M,), base poses (M, 4, 4))`` from ``global_pose.csv``."""
    table = read_table(path, 13, "MulRan global_pose.csv")
    stamps = read_stamp_column(path, "MulRan global_pose.csv")
    poses = np.tile(np.eye(4), (len(table), 1, 1))
    poses[:, :3, :4] = table[:, 1:].reshape(-1, 3, 4)
    return stamps, poses


def open_mulran(path: Path, poses: str | Path | None = None, calib=None,
                tolerance: float = TOLERANCE, **options) -> Sequence:
    """Open a MulRan sequence (the folder holding ``Ouster/``, or ``Ouster/`` itself)."""
    check_options("mulran", {**options, **({"calib": calib} if calib else {})})
    seq_dir = mulran_sequence(path) or (path.parent if path.name == "Ouster" else path)
    scans = list_files(seq_dir / "Ouster", ".bin", "MulRan Ouster scan")
    pose_path = Path(poses) if poses is not None else seq_dir / POSE_FILE
    if not pose_path.is_file():
        raise LirisError(pose_path, "MulRan pose file not found (global_pose.csv beside Ouster/)")
    stamps, base_poses = read_global_pose(pose_path)
    scan_ns = stem_stamps(scans, seq_dir / "Ouster")
    keep, matched, dropped = match_scans(ns_to_seconds(scan_ns, 10**9),
                                         ns_to_seconds(stamps, 10**9), base_poses, tolerance,
                                         pose_path)
    lidar = matched @ base_to_ouster()
    return build("mulran", seq_dir, seq_dir.name, pick(scans, keep), lidar, read_kitti_bin,
                 "os1-64-gen1", f"{pose_path} (base frame) · T_base_ouster",
                 times=ns_to_seconds(scan_ns[keep], 10**9), unmatched=dropped, frame_ids=keep)


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def mulran_sequence(path: Path) -> Path | None:
    """The MulRan sequence folder (holding ``Ouster/``) of a path, or None."""
    if path.name == "Ouster" and has_file(path.parent, "global_pose.csv"):
        return path.parent
    if has_dir(path, "Ouster") and has_file(path, "global_pose.csv"):
        return path
    return None


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "mulran", "MulRan",
        "<Seq>/Ouster/<ns>.bin + <Seq>/global_pose.csv (open <Seq> or <Seq>/Ouster)",
        "vehicle base frame, ns stamps, more rows than scans",
        "each scan gets the pose at its stamp (interpolated, named tolerance); "
        "T_base · T_base_ouster (calib_base2ouster.txt)",
        "os1-64-gen1", "Ouster/ beside global_pose.csv",
        lambda p: mulran_sequence(p) is not None, "mulran:open_mulran",
        frame=("Ouster OS1-64, z up: kept (its x points backwards on the car, base → Ouster yaw "
               "179.67°; not turned)"),
        intensity="the file's fourth f32 (Ouster intensity, raw counts), as stored"),
)
