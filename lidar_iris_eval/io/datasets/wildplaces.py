"""Wild-Places (forest, handheld VLP-16): accumulated *submaps*, not single scans.

* v3: ``<seq>/Clouds_downsampled/<time>.bin`` float32 × 4 and
  ``<seq>/submap_poses.csv`` (header ``%time,x,y,z,qx,qy,qz,qw``);
* v1/v2: ``<seq>/Clouds/<timestamp>.pcd`` and ``<seq>/poses_aligned.csv``
  (header ``timestamp,x,y,z,qx,qy,qz,qw``).

File names are the submap times (seconds); each submap gets the pose at its
time (within :data:`TOLERANCE`). The poses are those of the submaps' own
frame, so no extrinsic is applied. Wild-Places' own evaluation rules
(5 m / 300 s intra-sequence) are a ``--convention`` matter, not the reader's.
"""

from __future__ import annotations

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
from lidar_iris_eval.io.scans import read_kitti_bin
from lidar_iris_eval.io.sequence import Sequence

#: seconds between a submap's file-name time and the nearest pose row
TOLERANCE = 0.05


def read_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(seconds (M,), poses (M, 4, 4))`` of a Wild-Places pose csv."""
    table = read_table(path, 8, "Wild-Places pose", skip_header=True)
    return table[:, 0], se3(quat_xyzw(table[:, 4:8], path), table[:, 1:4])


def _stamps(paths: list[Path], folder: Path) -> np.ndarray:
    try:
        return np.array([float(p.name.rsplit(".", 1)[0]) for p in paths])
    except ValueError:
        raise LirisError(folder, "Wild-Places cloud names must be their times "
                                 "(<seconds>.pcd or <seconds>.bin)") from None


def _open(path: Path, clouds: str, suffix: str, pose_name: str, reader, dataset: str,
          poses, calib, tolerance, options) -> Sequence:
    check_options(dataset, {**options, **({"calib": calib} if calib else {})})
    seq_dir = path.parent if path.name == clouds else path
    files, times = list_by_time(seq_dir / clouds, suffix, f"Wild-Places {clouds}",
                                lambda found: _stamps(found, seq_dir / clouds))
    pose_path = Path(poses) if poses is not None else seq_dir / pose_name
    if not pose_path.is_file():
        raise LirisError(pose_path, f"Wild-Places pose file not found ({pose_name} beside "
                                    f"{clouds}/)")
    pose_times, submap_poses = read_poses(pose_path)
    keep, matched, dropped = match_scans(times, pose_times, submap_poses, tolerance, pose_path)
    return build(dataset, seq_dir, seq_dir.name, pick(files, keep), matched, reader, "vlp16",
                 f"{pose_path} (submap frame)", times=times[keep], unmatched=dropped,
                 frame_ids=keep)


def open_wild_v12(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                  **options) -> Sequence:
    """Open a Wild-Places v1/v2 sequence (``Clouds/`` + ``poses_aligned.csv``)."""
    return _open(path, "Clouds", ".pcd", "poses_aligned.csv", read_pcd, "wild-places",
                 poses, calib, tolerance, options)


def open_wild_v3(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                 **options) -> Sequence:
    """Open a Wild-Places v3 sequence (``Clouds_downsampled/`` + ``submap_poses.csv``)."""
    return _open(path, "Clouds_downsampled", ".bin", "submap_poses.csv", read_kitti_bin,
                 "wild-places-v3", poses, calib, tolerance, options)


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def _wild_v12(path: Path) -> bool:
    return has_file(path, "poses_aligned.csv") or (
        path.name == "Clouds" and has_file(path.parent, "poses_aligned.csv"))


def _wild_v3(path: Path) -> bool:
    return has_file(path, "submap_poses.csv") or (
        path.name == "Clouds_downsampled" and has_file(path.parent, "submap_poses.csv"))


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "wild-places", "Wild-Places v1/v2",
        "<seq>/Clouds/<time>.pcd + <seq>/poses_aligned.csv",
        "submap poses (timestamp,x,y,z,qx,qy,qz,qw); clouds are accumulated submaps",
        "pose matched to each submap's stamp; no extrinsic",
        "vlp16", "poses_aligned.csv",
        _wild_v12, "wildplaces:open_wild_v12",
        frame="submap frame, z up: kept",
        intensity="the PCD's intensity field as stored, else none"),
    DatasetSpec(
        "wild-places-v3", "Wild-Places v3",
        "<seq>/Clouds_downsampled/<time>.bin + <seq>/submap_poses.csv",
        "submap poses (%time,x,y,z,qx,qy,qz,qw); clouds are accumulated submaps",
        "pose matched to each submap's stamp; no extrinsic",
        "vlp16", "submap_poses.csv",
        _wild_v3, "wildplaces:open_wild_v3",
        frame="submap frame, z up: kept",
        intensity="the file's fourth f32, as stored"),
)
