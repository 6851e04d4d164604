"""Oxford Radar RobotCar: two HDL-32E, ``velodyne_left|right/<ts>.bin`` or raw ``<ts>.png``.

* ``.bin``: float32 stored **planar**, shape ``(4, N)``: all x, then all y, z,
  intensity (the SDK's ``python/velodyne.py`` reshapes to ``(4, -1)``);
  reading it as ``N × 4`` interleaved, as some loaders do, scrambles every point.
* ``.png`` (8-bit grey, 106 rows, one column per firing): rows 0-31 intensity,
  32-95 ranges (32 little-endian uint16 rows, · 0.002 m), 96-97 azimuth
  (uint16, · 2π / 36000), 98-105 int64 timestamps. Points follow the SDK's
  fixed HDL-32E elevations; returns of 1 m or less are invalid and dropped.

Poses: ``gps/ins.csv`` (µs; northing, easting, down, roll, pitch, yaw, the SDK's
Rz·Ry·Rx rotation), each scan getting the INS pose at its stamp (within
:data:`TOLERANCE`). The LiDAR pose is ``T_ins · inv(T_stereo_ins) ·
T_stereo_velodyne``, the SDK's ``extrinsics/ins.txt`` and
``extrinsics/<side>.txt`` (x y z roll pitch yaw, relative to the stereo
camera), read from ``extrinsics/`` in the run folder or its parent when
present, else the SDK's values below.

Frame: the SDK's Velodyne frame is z-down: its points put the HDL-32E's beams
at −10.7..+30.7° of "elevation" (``z = sin(e)·r`` with the SDK's elevation
table, whose real beams span +10.7..−30.7°), so the road lies at z ≈ +1.6 m,
and its extrinsics (``velodyne_left|right.txt``, yaw −3.134 / −3.136 rad from
the stereo camera's x-forward, y-right, z-down frame; ``ins.txt``, northing /
easting / down) make its x axis point backwards and its y axis left. liris turns
every scan by π about y (:data:`TO_LIRIS`: x → −x, z → −z, y kept) into its
x-forward, y-left, z-up frame (as KITTI), and the poses with it (``T ·
TO_LIRISᵀ``), so ground-truth distances are unchanged.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, read_text
from lidar_iris_eval.io.datasets.base import (
    build,
    check_options,
    list_files,
    match_scans,
    pick,
    rpy_zyx,
    se3,
    stem_stamps,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_dir, has_file
from lidar_iris_eval.io.poses import check_finite
from lidar_iris_eval.io.scans import Scan, clean_points
from lidar_iris_eval.io.sequence import Sequence

#: the SDK's extrinsics (x y z roll pitch yaw, metres and radians, relative to the stereo camera)
SDK_EXTRINSICS = {
    "ins": (-1.7132, 0.1181, 1.1948, -0.0125, 0.0400, 0.0050),
    "velodyne_left": (-0.60072, -0.34077, -0.26837, -0.0053948, -0.041998, -3.1337),
    "velodyne_right": (-0.61153, 0.55676, -0.27023, 0.0027052, -0.041999, -3.1357),
}
#: the SDK's HDL-32E beam elevations (radians), lowest first
HDL32E_ELEVATIONS = (
    -0.1862, -0.1628, -0.1396, -0.1164, -0.0930, -0.0698, -0.0466, -0.0232, 0.0, 0.0232,
    0.0466, 0.0698, 0.0930, 0.1164, 0.1396, 0.1628, 0.1862, 0.2094, 0.2327, 0.2560, 0.2793,
    0.3025, 0.3259, 0.3491, 0.3723, 0.3957, 0.4189, 0.4421, 0.4655, 0.4887, 0.5119, 0.5353,
)  # fmt: skip
RANGE_RESOLUTION = 0.002  # m per unit
MINIMUM_RANGE = 1.0  # m
BASE_TO_FIRE_HEIGHT = 0.090805  # m
PNG_ROWS = 106
#: the SDK's Velodyne frame (x backward, y left, z down on the car) -> liris's
#: (x forward, y left, z up): a half turn about y
TO_LIRIS = np.diag([-1.0, 1.0, -1.0])
#: seconds between a scan stamp and the nearest INS sample: one revolution of the
#: HDL-32E at the 20 Hz the scans are stamped at (50 ms apart; the INS runs at 50 Hz)
TOLERANCE = 0.05
INS_COLUMNS = ("timestamp", "northing", "easting", "down", "roll", "pitch", "yaw")


def read_planar_bin(path: Path) -> Scan:
    """A ``velodyne_*/<ts>.bin`` scan: float32 planar ``(4, N)``."""
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "scan file not found")
    size = path.stat().st_size
    if size % 16:
        raise LirisError(path, f"truncated or not an Oxford velodyne .bin: size {size} bytes is "
                               "not a multiple of 16 (planar float32 rows x, y, z, intensity)")
    data = np.fromfile(path, dtype="<f4").reshape(4, -1)
    return clean_points(data[:3].T, data[3], path)


def read_raw_png(path: Path) -> Scan:
    """A raw ``velodyne_*/<ts>.png`` scan, decoded as the SDK does."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        with Image.open(path) as image:
            if image.mode != "L":
                raise LirisError(path, f"Oxford raw velodyne .png must be 8-bit grey, "
                                       f"not mode {image.mode}")
            pixels = np.asarray(image, dtype=np.uint8)
    except (UnidentifiedImageError, OSError, SyntaxError) as err:
        raise LirisError(path, f"not a readable PNG ({err})") from None
    if pixels.ndim != 2 or pixels.shape[0] != PNG_ROWS:
        raise LirisError(path, f"Oxford raw velodyne .png has {pixels.shape[0]} rows, expected "
                               f"{PNG_ROWS} (32 intensity, 64 range, 2 azimuth, 8 time bytes)")
    intensity = pixels[0:32].astype(np.float32)
    ranges = np.ascontiguousarray(pixels[32:96].T).view("<u2").T * RANGE_RESOLUTION
    azimuth = np.ascontiguousarray(pixels[96:98].T).view("<u2").T * (2 * np.pi / 36000)
    elevation = np.asarray(HDL32E_ELEVATIONS)[:, None]
    valid = ranges > MINIMUM_RANGE
    z = np.sin(elevation) * ranges - BASE_TO_FIRE_HEIGHT
    planar = np.cos(elevation) * ranges
    x = np.sin(azimuth) * planar
    y = -np.cos(azimuth) * planar
    points = np.stack([x[valid], y[valid], z[valid]], axis=1)
    return clean_points(points, intensity[valid], path)


def extrinsic(run: Path, name: str) -> tuple[np.ndarray, str]:
    """``T_stereo_<name>`` from ``extrinsics/<name>.txt`` near the run, else the SDK value."""
    for place in (run / "extrinsics", run.parent / "extrinsics"):
        path = place / f"{name}.txt"
        if path.is_file():
            text = read_text(path, "extrinsics file").split()
            try:
                values = [float(v) for v in text[:6]]
            except ValueError:
                values = []
            if len(values) != 6:
                raise LirisError(path, "malformed extrinsics: expected x y z roll pitch yaw")
            check_finite(values, str(path), "extrinsics")
            return _xyzrpy(values), str(path)
    return _xyzrpy(SDK_EXTRINSICS[name]), f"SDK {name}.txt"


def _xyzrpy(values) -> np.ndarray:
    x, y, z, roll, pitch, yaw = values
    return se3(rpy_zyx(roll, pitch, yaw)[0], (x, y, z))


def read_ins(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(seconds (M,), INS poses (M, 4, 4))`` from ``gps/ins.csv`` (header names the columns)."""
    if not path.is_file():
        raise LirisError(path, "Oxford INS file not found (gps/ins.csv); give one with --poses")
    rows = list(csv.reader(read_text(path, "INS file").splitlines()))
    if not rows:
        raise LirisError(path, "INS file is empty")
    header = [h.strip() for h in rows[0]]
    missing = [c for c in INS_COLUMNS if c not in header]
    if missing:
        raise LirisError(path, f"INS header lacks {', '.join(missing)} (expected the SDK's "
                               "ins.csv columns)")
    cols = [header.index(c) for c in INS_COLUMNS]
    values = []
    for number, row in enumerate(rows[1:], start=2):
        if not row:
            continue
        try:
            values.append([float(row[c]) for c in cols])
        except (ValueError, IndexError):
            raise LirisError(f"{path}:{number}", "malformed INS row") from None
        check_finite(values[-1], f"{path}:{number}", "INS")
    if not values:
        raise LirisError(path, "INS file has no rows")
    table = np.asarray(values)
    poses = se3(rpy_zyx(table[:, 4], table[:, 5], table[:, 6]), table[:, 1:4])
    return table[:, 0] * 1e-6, poses


def _open(path: Path, suffix: str, reader, dataset: str, poses, calib, tolerance,
          options) -> Sequence:
    check_options(dataset, {**options, **({"calib": calib} if calib else {})})
    scan_dir = oxford_scan_dir(path) or path
    run = scan_dir.parent
    scans = list_files(scan_dir, suffix, f"Oxford {scan_dir.name}")
    stamps = stem_stamps(scans, scan_dir)
    pose_path = Path(poses) if poses is not None else run / "gps" / "ins.csv"
    ins_times, ins_poses = read_ins(pose_path)
    t_stereo_ins, ins_source = extrinsic(run, "ins")
    side = scan_dir.name if scan_dir.name in SDK_EXTRINSICS else "velodyne_left"
    t_stereo_lidar, lidar_source = extrinsic(run, side)
    ins_to_lidar = np.linalg.inv(t_stereo_ins) @ t_stereo_lidar
    keep, matched, dropped = match_scans(stamps * 1e-6, ins_times, ins_poses, tolerance, pose_path)
    return build(dataset, run, run.name, pick(scans, keep), matched @ ins_to_lidar, reader,
                 "hdl32", f"{pose_path} (INS) · inv({ins_source}) · {lidar_source}",
                 times=stamps[keep] * 1e-6, unmatched=dropped, frame_ids=keep,
                 to_liris=TO_LIRIS)


def open_oxford_bin(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                    **options) -> Sequence:
    """Open ``<run>/velodyne_left`` (or the run folder) of planar ``.bin`` scans."""
    return _open(path, ".bin", read_planar_bin, "oxford", poses, calib, tolerance, options)


def open_oxford_png(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                    **options) -> Sequence:
    """Open ``<run>/velodyne_left`` (or the run folder) of raw ``.png`` scans."""
    return _open(path, ".png", read_raw_png, "oxford-raw", poses, calib, tolerance, options)


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def oxford_scan_dir(path: Path) -> Path | None:
    """``<run>/velodyne_left`` (or ``_right``) of an Oxford Radar RobotCar path, or None."""
    if path.name in ("velodyne_left", "velodyne_right") and path.is_dir():
        return path
    for side in ("velodyne_left", "velodyne_right"):
        if has_dir(path, side) and has_file(path, f"{side}.timestamps"):
            return path / side
    return None


def _oxford_has(path: Path, suffix: str) -> bool:
    folder = oxford_scan_dir(path)
    return folder is not None and any(p.suffix == suffix for p in folder.iterdir())


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "oxford", "Oxford Radar RobotCar (velodyne .bin)",
        "<run>/velodyne_left/<ts>.bin + <run>/velodyne_left.timestamps + <run>/gps/ins.csv "
        "(extrinsics/ in <run> or its parent, else the SDK's values)",
        "INS (northing, easting, down, roll, pitch, yaw), µs",
        "planar 4×N float32 (never N×4); INS pose at each scan stamp; "
        "T_ins · inv(T_stereo_ins) · T_stereo_velodyne",
        "hdl32", "velodyne_left|right/ with .bin scans",
        lambda p: _oxford_has(p, ".bin"), "oxford:open_oxford_bin",
        frame=("SDK Velodyne frame x backward, y left, z down (extrinsic yaw ≈ π from the "
               "x-forward, y-right, z-down stereo frame) → turned by π about y (x' = −x, z' = −z)"
               " to x forward, y left, z up; poses turned alike"),
        intensity="the fourth planar f32 row (HDL-32E intensity, 0..255), as stored"),
    DatasetSpec(
        "oxford-raw", "Oxford Radar RobotCar (raw velodyne .png)",
        "<run>/velodyne_left/<ts>.png; timestamps, INS and extrinsics as for oxford",
        "INS, as for oxford",
        "rows 0-31 intensity, 32-95 ranges (uint16 · 2 mm), 96-97 azimuth; fixed HDL-32E "
        "elevations (SDK); returns under 1 m dropped; poses as for oxford",
        "hdl32", "velodyne_left|right/ with .png scans",
        lambda p: _oxford_has(p, ".png"), "oxford:open_oxford_png",
        frame="as oxford: the SDK's points (z down) turned by π about y",
        intensity="rows 0-31, u8 (0..255)"),
)
