"""The formats liris read before the registry: KITTI layout, GOSMatch objects, ROS bags, folders.

Each opener keeps the behaviour (and the messages) of its reader module.
"""

from __future__ import annotations

from pathlib import Path

from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_file
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


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def _objects(path: Path) -> bool:
    from lidar_iris_eval.io.objects import is_objects_layout

    return is_objects_layout(path)


def _kitti(path: Path) -> bool:
    from lidar_iris_eval.io.kitti import is_kitti_layout

    return is_kitti_layout(path)


def _rosbag(path: Path) -> bool:
    if path.is_file():
        return path.suffix in (".bag", ".db3", ".mcap")
    return has_file(path, "metadata.yaml")


def _folder(path: Path) -> bool:
    from lidar_iris_eval.io.sequence import SCAN_READERS

    return path.is_dir() and any(
        p.suffix.lower() in SCAN_READERS and p.is_file() for p in path.iterdir())


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "objects", "GOSMatch object layout",
        "a folder with bow.txt and centroids/ (the GOSMatch authors' files)",
        "KITTI camera frame", "inv(Tr) · T · Tr", None, "bow.txt + centroids/",
        _objects, "generic:open_objects_layout", generic=True,
        frame="KITTI Velodyne frame (object centroids): kept",
        intensity="none"),
    DatasetSpec(
        "kitti", "KITTI odometry / SemanticKITTI (and liris simulate)",
        "sequences/NN with velodyne/%06d.bin, calib.txt, poses.txt or ../../poses/NN.txt",
        "left camera frame", "inv(Tr) · T · Tr", "hdl64", "velodyne/",
        _kitti, "generic:open_kitti_layout", generic=True,
        frame="Velodyne, x forward, y left, z up (the reference): kept",
        intensity="the file's reflectance (f32, 0..1 on KITTI), as stored"),
    DatasetSpec(
        "rosbag", "ROS 1 / ROS 2 bag",
        "a .bag, .db3 or .mcap file, or a ROS 2 bag folder (metadata.yaml)",
        "as published (odometry / pose topic or a pose file)",
        "pose at each message stamp (see docs)", None, ".bag/.db3/.mcap or metadata.yaml",
        _rosbag, "generic:open_rosbag_file", generic=True,
        frame="the cloud's frame as published: kept (not turned)",
        intensity="the message's intensity field as published, else none"),
    DatasetSpec(
        "folder", "folder of scans",
        "a folder of .bin/.npy/.pcd scans with poses.txt, poses_tum.txt or *.tum",
        "KITTI camera frame (calib.txt) or LiDAR (--lidar-frame-poses)",
        "inv(Tr) · T · Tr, or none; TUM poses matched by time", None,
        ".bin/.npy/.pcd scan files", _folder, "generic:open_scan_folder", generic=True,
        frame="as stored: kept (not turned)",
        intensity="the file's fourth column / intensity field as stored, else none"),
)
