"""The formats liris read before the registry: KITTI layout, GOSMatch objects, ROS bags, folders.

Each opener keeps the behaviour (and the messages) of its reader module.
"""

from __future__ import annotations

from pathlib import Path

from lidar_iris_eval.io.sequence import Sequence


def open_objects_layout(path: Path, poses=None, calib=None, **options) -> Sequence:
    """The GOSMatch authors' ``bow.txt`` + ``centroids/`` layout."""
    from lidar_iris_eval.io.objects import open_objects

    return open_objects(path, poses=poses, calib=calib, **options)


def open_kitti_layout(path: Path, poses=None, calib=None, **options) -> Sequence:
    """A KITTI odometry sequence (or ``liris simulate`` output)."""
    from lidar_iris_eval.io import selection
    from lidar_iris_eval.io.kitti import open_kitti

    if selection.needs_folder_reader(poses, options):  # TUM poses, times, pose options
        return selection.open_kitti_with_options(path, poses, calib, **options)
    return open_kitti(path, poses=poses, calib=calib)


def open_rosbag_file(path: Path, poses=None, calib=None, **options) -> Sequence:
    """A ROS 1 or ROS 2 bag (``calib`` is not used for bags)."""
    from lidar_iris_eval.io.rosbag import open_rosbag

    return open_rosbag(path, poses=poses, **options)


def open_scan_folder(path: Path, poses=None, calib=None, **options) -> Sequence:
    """A folder of ``.bin``/``.npy``/``.pcd`` scans with a pose file."""
    from lidar_iris_eval.io.folder import open_folder

    return open_folder(path, poses=poses, calib=calib, **options)
