"""Apollo-SouthBay: ``<route>/<date>/pcds/<n>.pcd`` and ``poses/gt_poses.txt``.

``gt_poses.txt`` has 9 columns, ``index time x y z qx qy qz qw``: the LiDAR
pose of scan ``<index>.pcd``. Scans are paired with poses by that index (not
by row order); a scan without a pose row is dropped and counted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, warn
from lidar_iris_eval.io.datasets.base import (
    build,
    check_options,
    list_files,
    pick,
    quat_xyzw,
    read_table,
    se3,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_file
from lidar_iris_eval.io.pcd import read_pcd
from lidar_iris_eval.io.sequence import Sequence


def open_apollo(path: Path, poses=None, calib=None, tolerance=None, **options) -> Sequence:
    """Open an Apollo-SouthBay ``<route>/<date>`` folder (or its ``pcds/``).

    ``tolerance`` is accepted and unused: scans pair with poses by index.
    """
    check_options("apollo", {**options, **({"calib": calib} if calib else {})})
    seq_dir = path.parent if path.name == "pcds" else path
    scans = list_files(seq_dir / "pcds", ".pcd", "Apollo-SouthBay pcds")
    try:
        numbers = np.array([int(p.name[:-4]) for p in scans])
    except ValueError:
        raise LirisError(seq_dir / "pcds", "Apollo-SouthBay scans are named <n>.pcd") from None
    pose_path = Path(poses) if poses is not None else seq_dir / "poses" / "gt_poses.txt"
    table = read_table(pose_path, 9, "Apollo-SouthBay gt_poses")
    by_index = {int(i): row for row, i in enumerate(table[:, 0])}
    keep = np.array([k for k, n in enumerate(numbers) if int(n) in by_index], dtype=np.int64)
    if len(keep) == 0:
        raise LirisError(pose_path, "no pcd file number appears in the index column")
    dropped = len(scans) - len(keep)
    if dropped:
        warn(pose_path, f"dropped {dropped} of {len(scans)} scans with no pose row")
    rows = table[[by_index[int(numbers[k])] for k in keep]]
    lidar = se3(quat_xyzw(rows[:, 5:9], pose_path), rows[:, 2:5])
    return build("apollo", seq_dir, f"{seq_dir.parent.name}-{seq_dir.name}", pick(scans, keep),
                 lidar, read_pcd, "hdl64", f"{pose_path} (LiDAR frame)", times=rows[:, 1],
                 unmatched=dropped, frame_ids=numbers[keep])


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def _apollo(path: Path) -> bool:
    return has_file(path, "poses", "gt_poses.txt") or (
        path.name == "pcds" and has_file(path.parent, "poses", "gt_poses.txt"))


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "apollo", "Apollo-SouthBay",
        "<route>/<date>/pcds/<n>.pcd + <route>/<date>/poses/gt_poses.txt",
        "LiDAR frame (index, time, x, y, z, qx, qy, qz, qw)",
        "pose by the index column = pcd file number; no extrinsic",
        "hdl64", "poses/gt_poses.txt",
        _apollo, "apollo:open_apollo",
        frame="LiDAR frame, z up: kept",
        intensity="the PCD's intensity field as stored, else none"),
)
