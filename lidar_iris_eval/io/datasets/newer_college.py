"""Newer College 2020: ``raw_format/ouster_scan/cloud_<sec>_<nsec>.pcd`` + base-frame poses.

``ground_truth/registered_poses.csv`` (``sec,nsec,x,y,z,qx,qy,qz,qw``) gives the
*base* frame; each scan gets the pose at its stamp (within :data:`TOLERANCE`)
and the LiDAR pose is ``T_base · T_CL`` with the OS1-64 extrinsic of kiss-icp's
``ncd.py``: q = (0, 0, 0.924, 0.383) (x, y, z, w), t = (−0.084, −0.025, 0.050) m.
The same data as ROS bags (``/os1_cloud_node/points``) opens with the rosbag reader.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.datasets.base import (
    build,
    check_options,
    list_by_time,
    match_scans,
    pick,
    quat_xyzw,
    read_table,
    se3,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_file
from lidar_iris_eval.io.pcd import read_pcd
from lidar_iris_eval.io.sequence import Sequence

T_CL_QUAT_XYZW = (0.0, 0.0, 0.924, 0.383)
T_CL_T = (-0.084, -0.025, 0.050)
#: seconds between a scan stamp and the nearest ground-truth pose
TOLERANCE = 0.1
_NAME = re.compile(r"^cloud_(\d+)_(\d+)\.pcd$")


def base_to_lidar() -> np.ndarray:
    """``T_CL``: maps OS1-64 points into the base frame."""
    return se3(quat_xyzw(np.array(T_CL_QUAT_XYZW), "T_CL")[0], T_CL_T)


def _stamp(path: Path) -> float:
    match = _NAME.match(path.name)
    if match is None:
        raise LirisError(path, "Newer College scans are named cloud_<sec>_<nsec>.pcd")
    return int(match.group(1)) + int(match.group(2)) * 1e-9


def open_newer_college(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                       **options) -> Sequence:
    """Open a Newer College 2020 sequence root (or its ``raw_format/ouster_scan``)."""
    check_options("newer-college", {**options, **({"calib": calib} if calib else {})})
    root = path.parent.parent if path.name == "ouster_scan" else path
    scans, times = list_by_time(root / "raw_format" / "ouster_scan", ".pcd",
                                "Newer College ouster_scan",
                                lambda files: np.array([_stamp(p) for p in files]))
    pose_path = Path(poses) if poses is not None else (
        root / "ground_truth" / "registered_poses.csv")
    table = read_table(pose_path, 9, "Newer College pose", skip_header=True)
    base = se3(quat_xyzw(table[:, 5:9], pose_path), table[:, 2:5])
    pose_times = table[:, 0] + table[:, 1] * 1e-9
    keep, matched, dropped = match_scans(times, pose_times, base, tolerance, pose_path)
    return build("newer-college", root, root.name, pick(scans, keep), matched @ base_to_lidar(),
                 read_pcd, "os1-64-gen1", f"{pose_path} (base frame) · T_CL", times=times[keep],
                 unmatched=dropped, frame_ids=keep)


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def _newer_college(path: Path) -> bool:
    return has_file(path, "ground_truth", "registered_poses.csv") or (
        path.name == "ouster_scan" and path.parent.name == "raw_format")


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "newer-college", "Newer College 2020",
        "<root>/raw_format/ouster_scan/cloud_<sec>_<nsec>.pcd + "
        "<root>/ground_truth/registered_poses.csv",
        "base frame, sec,nsec,x,y,z,qx,qy,qz,qw",
        "pose at each scan stamp; T_base · T_CL (q = 0, 0, 0.924, 0.383; "
        "t = −0.084, −0.025, 0.050)",
        "os1-64-gen1", "ground_truth/registered_poses.csv",
        _newer_college, "newer_college:open_newer_college",
        frame="Ouster OS1-64, z up: kept",
        intensity="the PCD's intensity field as stored, else none"),
)
