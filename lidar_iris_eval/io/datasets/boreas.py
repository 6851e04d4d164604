"""Boreas: ``lidar/<µs>.bin`` float32 × 6 and ``applanix/lidar_poses.csv`` LiDAR poses in ENU.

A record is x, y, z, intensity, laser id, time (24 bytes). ``lidar_poses.csv``
(header ``GPSTime,x,y,z,vx,vy,vz,roll,pitch,yaw,wz,wy,wx``) holds one LiDAR
pose per scan; its rotation follows pyboreas (``yawPitchRollToRot``):
``C = roll(r) · pitch(p) · yaw(y)`` with pyboreas' elementary matrices, which
are the *transposes* of the usual active rotations. No extrinsic is applied.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.io.datasets.base import (
    build,
    check_options,
    list_files,
    match_scans,
    pick,
    read_records,
    read_stamp_column,
    read_table,
    record_dtype,
    se3,
    stem_stamps,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_file
from lidar_iris_eval.io.scans import Scan, clean_points
from lidar_iris_eval.io.sequence import Sequence

POINT = record_dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                      ("laser_id", "<f4"), ("time", "<f4")])
#: seconds between a scan stamp and the nearest pose row (one row per scan)
TOLERANCE = 0.05


def read_boreas_scan(path: Path) -> Scan:
    """One Boreas scan."""
    data = read_records(path, POINT, "Boreas lidar")
    return clean_points(np.stack([data["x"], data["y"], data["z"]], axis=1), data["intensity"],
                        path)


def pyboreas_rotation(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """``roll(r) @ pitch(p) @ yaw(y)`` with pyboreas' (passive) elementary rotations."""
    n = len(roll)
    c, s = np.cos, np.sin
    rx = np.zeros((n, 3, 3))
    rx[:, 0, 0] = 1
    rx[:, 1, 1], rx[:, 1, 2], rx[:, 2, 1], rx[:, 2, 2] = c(roll), s(roll), -s(roll), c(roll)
    ry = np.zeros((n, 3, 3))
    ry[:, 1, 1] = 1
    ry[:, 0, 0], ry[:, 0, 2], ry[:, 2, 0], ry[:, 2, 2] = c(pitch), -s(pitch), s(pitch), c(pitch)
    rz = np.zeros((n, 3, 3))
    rz[:, 2, 2] = 1
    rz[:, 0, 0], rz[:, 0, 1], rz[:, 1, 0], rz[:, 1, 1] = c(yaw), s(yaw), -s(yaw), c(yaw)
    return rx @ ry @ rz


def open_boreas(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                **options) -> Sequence:
    """Open a Boreas sequence folder (or its ``lidar/``)."""
    check_options("boreas", {**options, **({"calib": calib} if calib else {})})
    seq_dir = path.parent if path.name == "lidar" else path
    scans = list_files(seq_dir / "lidar", ".bin", "Boreas lidar scan")
    stamps = stem_stamps(scans, seq_dir / "lidar")
    pose_path = Path(poses) if poses is not None else seq_dir / "applanix" / "lidar_poses.csv"
    table = read_table(pose_path, 13, "Boreas lidar_poses.csv", skip_header=True)
    pose_us = read_stamp_column(pose_path, "Boreas lidar_poses.csv")
    lidar = se3(pyboreas_rotation(table[:, 7], table[:, 8], table[:, 9]), table[:, 1:4])
    keep, matched, dropped = match_scans(stamps * 1e-6, pose_us * 1e-6, lidar, tolerance,
                                         pose_path)
    return build("boreas", seq_dir, seq_dir.name, pick(scans, keep), matched, read_boreas_scan,
                 None, f"{pose_path} (LiDAR frame, ENU)", times=stamps[keep] * 1e-6,
                 unmatched=dropped, frame_ids=keep)


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def _boreas(path: Path) -> bool:
    return has_file(path, "applanix", "lidar_poses.csv") or (
        path.name == "lidar" and has_file(path.parent, "applanix", "lidar_poses.csv"))


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "boreas", "Boreas",
        "<seq>/lidar/<µs>.bin + <seq>/applanix/lidar_poses.csv",
        "LiDAR frame in ENU (GPSTime µs, x, y, z, …, roll, pitch, yaw)",
        "float32 × 6 records; pyboreas rotation convention; pose at each scan stamp",
        None, "applanix/lidar_poses.csv",
        _boreas, "boreas:open_boreas",
        frame="Velodyne Alpha Prime frame, z up: kept",
        intensity="the record's fourth f32, as stored"),
)
