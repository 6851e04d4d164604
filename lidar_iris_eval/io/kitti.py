"""The KITTI odometry layout.

::

    dataset/
      sequences/00/velodyne/000000.bin ...   scans
      sequences/00/labels/000000.label ...   SemanticKITTI labels (optional)
      sequences/00/calib.txt                 Tr (Velodyne -> camera)
      sequences/00/times.txt                 seconds, one per scan (optional)
      sequences/00/poses.txt                 camera poses (or:)
      poses/00.txt                           camera poses beside sequences/

Simulator output (``liris simulate``) uses the same layout with ``poses.txt``
inside the sequence folder.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.poses import camera_to_lidar, read_calib, read_kitti_poses
from lidar_iris_eval.io.sequence import (
    Sequence,
    check_counts,
    find_labels,
    list_scans,
    read_times,
)


def is_kitti_layout(path: Path) -> bool:
    """True for a folder with a ``velodyne/`` subfolder (or the velodyne folder itself)."""
    return (path / "velodyne").is_dir() or (path.name == "velodyne" and path.is_dir())


def find_kitti_poses(seq_dir: Path) -> Path | None:
    """``poses.txt`` in the sequence folder, else ``../../poses/<name>.txt``."""
    local = seq_dir / "poses.txt"
    if local.is_file():
        return local
    beside = seq_dir.parent.parent / "poses" / f"{seq_dir.name}.txt"
    return beside if beside.is_file() else None


def read_camera_poses_and_calib(
    pose_path: Path, calib_path: Path, scans: int | list[Path], scans_dir: Path
) -> tuple[np.ndarray, np.ndarray]:
    """KITTI camera-frame poses (one per scan, checked) and the ``Tr`` that converts them.

    Shared by every reader whose poses are KITTI camera poses: the KITTI
    layout and the GOSMatch object layout.
    """
    camera_poses = read_kitti_poses(pose_path)
    check_counts(scans, len(camera_poses), scans_dir, pose_path)
    if not calib_path.is_file():
        raise LirisError(calib_path, "calibration file not found (needed for LiDAR-frame poses)")
    return camera_poses, read_calib(calib_path)


def open_kitti(
    path: str | Path, poses: str | Path | None = None, calib: str | Path | None = None
) -> Sequence:
    """Open a KITTI-layout sequence lazily; poses are converted to the LiDAR frame.

    ``poses`` and ``calib`` override the files found in the layout.
    """
    seq_dir = Path(path)
    if seq_dir.name == "velodyne":
        seq_dir = seq_dir.parent
    scan_paths = list_scans(seq_dir / "velodyne")
    pose_path = Path(poses) if poses is not None else find_kitti_poses(seq_dir)
    if pose_path is None:
        raise LirisError(
            seq_dir, f"no poses: expected {seq_dir / 'poses.txt'} or ../../poses/{seq_dir.name}.txt"
        )
    calib_path = Path(calib) if calib is not None else seq_dir / "calib.txt"
    camera_poses, tr = read_camera_poses_and_calib(
        pose_path, calib_path, scan_paths, seq_dir / "velodyne"
    )
    times = None
    times_path = seq_dir / "times.txt"
    if times_path.is_file():
        times = read_times(times_path)
        check_counts(scan_paths, len(times), seq_dir / "velodyne", times_path, "times")
    labels_dir = seq_dir / "labels"
    return Sequence(
        name=seq_dir.name,
        path=seq_dir,
        scan_paths=scan_paths,
        poses=camera_to_lidar(camera_poses, tr),
        camera_poses=camera_poses,
        times=times,
        calib=tr,
        label_paths=find_labels(labels_dir, scan_paths),
        labels_dir=labels_dir,
    )
