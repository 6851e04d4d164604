"""KITTI-360: ``data_3d_raw/<drive>/velodyne_points/data/%010d.bin`` and sparse IMU poses.

Scans are float32 × 4 (x, y, z, reflectance) in the Velodyne frame;
``velodyne_points/timestamps.txt`` holds one date-time per scan.
``data_poses/<drive>/poses.txt`` has a row per *posed* frame, ``frame r00 ..
r23`` (IMU/GPS → world), and not every frame has one: each LiDAR frame inside
the posed range gets the pose interpolated by frame index (slerp + linear,
as pyLiDAR-SLAM's ``kitti_360_dataset.py``); frames before the first or after
the last posed frame are dropped and counted. With ``tolerance`` (seconds) a
frame whose nearest posed frame is further away in time is dropped too.
The LiDAR pose is ``T · cam0_to_pose · inv(cam_to_velo)`` with
``calibration/calib_cam_to_pose.txt`` (``image_00:``) and
``calibration/calib_cam_to_velo.txt``.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, read_text, warn
from lidar_iris_eval.io.datasets.base import build, check_options, list_files, pick, read_table
from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_dir
from lidar_iris_eval.io.poses import to_homogeneous
from lidar_iris_eval.io.scans import read_kitti_bin
from lidar_iris_eval.io.sequence import Sequence
from lidar_iris_eval.io.timematch import interpolate_poses


def read_sparse_poses(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(frame indices (M,), IMU poses (M, 4, 4))`` of a KITTI-360 ``poses.txt``."""
    table = read_table(path, 13, "KITTI-360 pose")
    return table[:, 0].astype(np.int64), to_homogeneous(table[:, 1:])


def read_calibration(folder: Path) -> np.ndarray:
    """``cam0_to_pose · inv(cam_to_velo)``: maps Velodyne points into the IMU/GPS frame."""
    pose_file = folder / "calib_cam_to_pose.txt"
    velo_file = folder / "calib_cam_to_velo.txt"
    for path in (pose_file, velo_file):
        if not path.is_file():
            raise LirisError(path, "KITTI-360 calibration file not found (calibration/ beside "
                                   "data_3d_raw; or give the folder with --calib)")
    cam0 = None
    for number, line in enumerate(read_text(pose_file, "calibration").splitlines(), start=1):
        key, _, rest = line.partition(":")
        if key.strip() == "image_00":
            cam0 = _twelve(rest.split(), f"{pose_file}:{number}")
    if cam0 is None:
        raise LirisError(pose_file, "no 'image_00:' line (camera 0 to pose)")
    velo = _twelve(read_text(velo_file, "calibration").split(), str(velo_file))
    return cam0 @ np.linalg.inv(velo)


def _twelve(values: list[str], source: str) -> np.ndarray:
    try:
        numbers = np.array([float(v) for v in values])
    except ValueError:
        raise LirisError(source, "malformed calibration (not numbers)") from None
    if numbers.size != 12:
        raise LirisError(source, f"malformed calibration: {numbers.size} numbers, expected 12")
    return to_homogeneous(numbers[None])[0]


def read_timestamps(path: Path, n_scans: int) -> np.ndarray:
    """Seconds (since the epoch, ns-exact split) of ``timestamps.txt`` date-times."""
    lines = [ln.strip() for ln in read_text(path, "timestamps file").splitlines() if ln.strip()]
    try:
        stamps = np.array([np.datetime64(ln.replace(" ", "T"), "ns") for ln in lines])
    except ValueError:
        raise LirisError(path, "malformed timestamps (expected 'YYYY-MM-DD hh:mm:ss.fffffffff')"
                         ) from None
    if len(stamps) != n_scans:
        raise LirisError(path, f"{len(stamps)} timestamps but {n_scans} scans; counts must be "
                               "equal")
    ns = stamps.astype(np.int64)
    return (ns // 10**9).astype(np.float64) + (ns % 10**9) * 1e-9


def open_kitti360(path: Path, poses=None, calib=None, tolerance: float | None = None,
                  **options) -> Sequence:
    """Open a KITTI-360 drive (``data_3d_raw/<drive>``, its velodyne_points/ or data/)."""
    check_options("kitti360", options)
    drive = kitti360_drive(path)
    if drive is None:
        raise LirisError(path, "not a KITTI-360 drive folder (<date>_drive_<NNNN>_sync with "
                               "velodyne_points/)")
    root = drive.parent.parent
    scans = list_files(drive / "velodyne_points" / "data", ".bin", "KITTI-360 velodyne")
    frames = np.array([int(p.stem) for p in scans], dtype=np.int64)
    stamps_path = drive / "velodyne_points" / "timestamps.txt"
    times = read_timestamps(stamps_path, len(scans)) if stamps_path.is_file() else None
    pose_path = Path(poses) if poses is not None else (
        root / "data_poses" / drive.name / "poses.txt")
    pose_frames, imu = read_sparse_poses(pose_path)
    calib_dir = Path(calib) if calib is not None else root / "calibration"
    imu_to_velo = read_calibration(calib_dir)
    inside = (frames >= pose_frames.min()) & (frames <= pose_frames.max())
    interpolated, _ = interpolate_poses(pose_frames.astype(np.float64), imu,
                                        frames.astype(np.float64), tolerance=np.inf)
    keep_mask = inside.copy()
    if tolerance is not None:
        if times is None:
            raise LirisError(f"--tolerance {tolerance}", f"needs {stamps_path} to time frames")
        by_frame = dict(zip(frames.tolist(), times, strict=True))
        posed_times = np.array([by_frame.get(int(f), np.nan) for f in pose_frames])
        posed_times = np.sort(posed_times[np.isfinite(posed_times)])
        right = np.clip(np.searchsorted(posed_times, times), 0, len(posed_times) - 1)
        left = np.clip(right - 1, 0, len(posed_times) - 1)
        nearest = np.minimum(np.abs(times - posed_times[left]), np.abs(times - posed_times[right]))
        keep_mask &= nearest <= tolerance
    keep = np.flatnonzero(keep_mask)
    if len(keep) == 0:
        raise LirisError(pose_path, "no LiDAR frame lies inside the posed frame range "
                                    f"{pose_frames.min()}..{pose_frames.max()}")
    dropped = len(scans) - len(keep)
    if dropped:
        warn(pose_path, f"dropped {dropped} of {len(scans)} scans outside the posed frames "
                        f"{pose_frames.min()}..{pose_frames.max()}"
             + ("" if tolerance is None else f" or over {tolerance} s from a posed frame"))
    return build("kitti360", drive, drive.name, pick(scans, keep),
                 interpolated[keep] @ imu_to_velo, read_kitti_bin, "hdl64",
                 f"{pose_path} (IMU, interpolated) · cam0_to_pose · inv(cam_to_velo)",
                 times=None if times is None else times[keep], unmatched=dropped,
                 frame_ids=frames[keep])


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


_KITTI360_DRIVE = re.compile(r"^\d{4}_\d{2}_\d{2}_drive_\d{4}_sync$")


def kitti360_drive(path: Path) -> Path | None:
    """The ``<date>_drive_<NNNN>_sync`` folder of a KITTI-360 path, or None."""
    for candidate in (path, path.parent, path.parent.parent):
        if _KITTI360_DRIVE.match(candidate.name) and has_dir(candidate, "velodyne_points"):
            return candidate
    return None


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "kitti360", "KITTI-360",
        "KITTI-360/data_3d_raw/<date>_drive_<NNNN>_sync (velodyne_points/data/%010d.bin); "
        "data_poses/<drive>/poses.txt and calibration/ beside data_3d_raw",
        "IMU/GPS → world, only for some frames (frame index + 3×4)",
        "interpolated to every LiDAR frame by frame index (slerp + linear; frames outside the "
        "posed range dropped), then T · cam0_to_pose · inv(cam_to_velo)",
        "hdl64", "a *_drive_NNNN_sync folder with velodyne_points/",
        lambda p: kitti360_drive(p) is not None, "kitti360:open_kitti360",
        frame="Velodyne HDL-64E, x forward, y left, z up: kept",
        intensity="the file's reflectance (f32, 0..1), as stored"),
)
