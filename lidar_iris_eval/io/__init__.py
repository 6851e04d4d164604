"""Sequence readers: one small module per on-disk format.

:func:`open_sequence` picks the reader from what is on disk (or from
``dataset=``) through the registry in :mod:`lidar_iris_eval.io.datasets`.
"""

from __future__ import annotations

from pathlib import Path

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.scans import Scan
from lidar_iris_eval.io.sequence import Sequence


def open_sequence(
    path: str | Path,
    poses: str | Path | None = None,
    calib: str | Path | None = None,
    **options,
) -> Sequence:
    """Open a sequence of a registered dataset, a KITTI layout, a folder of scans or a ROS bag.

    Parameters
    ----------
    path : a dataset folder as ``liris datasets`` lists (e.g. a MulRan
        sequence, ``<seq>/LiDAR/Aeva`` of HeLiPR), a KITTI sequence folder
        (with ``velodyne/``), a folder of ``.bin``/``.npy``/``.pcd`` scans, or a ROS bag.
    poses, calib : pose and calibration files overriding the ones found.
    options : ``dataset`` forces a registered reader (else it is detected,
        see :mod:`lidar_iris_eval.io.datasets`); format-specific options
        (e.g. ``pose_format``, ``lidar_frame`` for scan folders; ``topic``
        for bags; ``tolerance`` for every time-matched reader).
    """
    path = Path(path)
    if not path.exists():
        raise LirisError(path, "no such file or folder")
    from lidar_iris_eval.io import selection

    chosen = {k: options.pop(k) for k in selection.SELECTION_KEYS if k in options}
    if chosen:  # frames, every, min_distance: the same for every format
        return selection.select_frames(open_sequence(path, poses, calib, **options), **chosen)
    from lidar_iris_eval.io.datasets import find_dataset

    spec = find_dataset(path, options.pop("dataset", None))
    return spec.open(path, poses=poses, calib=calib, **options)


__all__ = ["Scan", "Sequence", "open_sequence"]
