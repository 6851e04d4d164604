"""Sequence readers: one small module per on-disk format.

:func:`open_sequence` picks the reader from what is on disk.
"""

from __future__ import annotations

from pathlib import Path

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.kitti import is_kitti_layout, open_kitti
from lidar_iris_eval.io.scans import Scan
from lidar_iris_eval.io.sequence import Sequence


def open_sequence(
    path: str | Path,
    poses: str | Path | None = None,
    calib: str | Path | None = None,
    **options,
) -> Sequence:
    """Open a sequence from a KITTI layout, a folder of scans, or a ROS bag.

    Parameters
    ----------
    path : a KITTI sequence folder (with ``velodyne/``), a folder of
        ``.bin``/``.npy``/``.pcd`` scans, or a ROS bag.
    poses, calib : pose and calibration files overriding the ones found.
    options : format-specific options (e.g. ``pose_format``, ``lidar_frame``
        for scan folders; ``topic`` for bags).
    """
    path = Path(path)
    if not path.exists():
        raise LirisError(path, "no such file or folder")
    from lidar_iris_eval.io import selection

    chosen = {k: options.pop(k) for k in selection.SELECTION_KEYS if k in options}
    if chosen:  # frames, every, min_distance: the same for every format
        return selection.select_frames(open_sequence(path, poses, calib, **options), **chosen)
    from lidar_iris_eval.io.objects import is_objects_layout, open_objects

    if is_objects_layout(path):  # the GOSMatch authors' bow.txt + centroids/
        return open_objects(path, poses=poses, calib=calib, **options)
    if is_kitti_layout(path):
        if selection.needs_folder_reader(poses, options):  # TUM poses, times, pose options
            return selection.open_kitti_with_options(path, poses, calib, **options)
        return open_kitti(path, poses=poses, calib=calib)
    if _is_rosbag(path):
        from lidar_iris_eval.io.rosbag import open_rosbag

        return open_rosbag(path, poses=poses, **options)
    if path.is_dir():
        from lidar_iris_eval.io.folder import open_folder

        return open_folder(path, poses=poses, calib=calib, **options)
    raise LirisError(path, "not a sequence: expected a folder of scans or a ROS bag")


def _is_rosbag(path: Path) -> bool:
    if path.is_file():
        return path.suffix in (".bag", ".db3", ".mcap")
    return (path / "metadata.yaml").is_file()


__all__ = ["Scan", "Sequence", "open_sequence"]
