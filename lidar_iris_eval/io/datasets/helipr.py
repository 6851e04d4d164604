"""HeLiPR: four LiDARs, ``<seq>/LiDAR/<Sensor>/<ns>.bin`` packed records, per-sensor GT.

Record layouts (little-endian, packed; HeLiPR-File-Player ``src/ROSThread.cpp``):

========  ===============================================================  =====
Ouster    f32 x, y, z, intensity, u32 t (ns), u16 reflectivity, ring, ambient  26 B
Velodyne  f32 x, y, z, intensity, u16 ring, f32 time                           22 B
Aeva      f32 x, y, z, reflectivity, velocity, i32 time offset (ns), u8 line,  25 B
          + f32 intensity only in files stamped after 1691936557946849179      29 B
Avia      f32 x, y, z, u8 reflectivity, u8 tag, u8 line, u32 offset time       19 B
========  ===============================================================  =====

Intensity is the ``intensity`` field where the record has one, else the
reflectivity (Aeva files before the switch, Avia). Ground truth:
``<seq>/LiDAR_GT/global_<Sensor>_gt.txt``, ``t x y z qx qy qz qw`` (t in ns),
already in that LiDAR's frame; each scan gets the pose at its stamp (within
:data:`TOLERANCE`).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.datasets.base import (
    build,
    check_options,
    list_files,
    match_scans,
    ns_to_seconds,
    pick,
    quat_xyzw,
    read_records,
    read_stamp_column,
    read_table,
    record_dtype,
    se3,
    stem_stamps,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec
from lidar_iris_eval.io.scans import Scan, clean_points
from lidar_iris_eval.io.sequence import Sequence

RECORDS = {
    "Ouster": record_dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                            ("t", "<u4"), ("reflectivity", "<u2"), ("ring", "<u2"),
                            ("ambient", "<u2")]),
    "Velodyne": record_dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                              ("ring", "<u2"), ("time", "<f4")]),
    "Aeva": record_dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("reflectivity", "<f4"),
                          ("velocity", "<f4"), ("time_offset", "<i4"), ("line_index", "u1")]),
    "Aeva-intensity": record_dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                    ("reflectivity", "<f4"), ("velocity", "<f4"),
                                    ("time_offset", "<i4"), ("line_index", "u1"),
                                    ("intensity", "<f4")]),
    "Avia": record_dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("reflectivity", "u1"),
                          ("tag", "u1"), ("line", "u1"), ("offset_time", "<u4")]),
}
#: Aeva files stamped after this (ns) carry the trailing f32 intensity (29-byte records)
AEVA_INTENSITY_AFTER = 1691936557946849179
HELIPR_SENSORS = ("Ouster", "Velodyne", "Aeva", "Avia")
SENSOR_PRESETS = {"Ouster": "os2-128", "Velodyne": "vlp16", "Aeva": None, "Avia": "avia"}
#: seconds between a scan stamp and the nearest ground-truth row (one row per scan)
TOLERANCE = 0.05


def record_for(sensor: str, stamp_ns: int) -> np.dtype:
    """The record layout of a ``sensor`` file stamped ``stamp_ns``."""
    if sensor == "Aeva" and stamp_ns > AEVA_INTENSITY_AFTER:
        return RECORDS["Aeva-intensity"]
    return RECORDS[sensor]


def read_helipr_scan(path: Path, sensor: str) -> Scan:
    """One HeLiPR scan of ``sensor`` (the Aeva layout chosen by the file's stamp)."""
    path = Path(path)
    try:
        stamp = int(path.stem)
    except ValueError:
        raise LirisError(path, "HeLiPR scan names are ns stamps (<ns>.bin)") from None
    dtype = record_for(sensor, stamp)
    what = f"HeLiPR {sensor}"
    if sensor == "Aeva":
        what += (" (29-byte records after stamp " if dtype.itemsize == 29 else
                 " (25-byte records up to stamp ") + f"{AEVA_INTENSITY_AFTER})"
    data = read_records(path, dtype, what)
    names = dtype.names
    intensity = data["intensity"] if "intensity" in names else data["reflectivity"]
    points = np.stack([data["x"], data["y"], data["z"]], axis=1)
    return clean_points(points, intensity.astype(np.float32), path)


def read_ground_truth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps ns (M,), LiDAR poses (M, 4, 4))`` of a ``global_<Sensor>_gt.txt``."""
    table = read_table(path, 8, "HeLiPR ground truth")
    stamps = read_stamp_column(path, "HeLiPR ground truth")
    return stamps, se3(quat_xyzw(table[:, 4:8], path), table[:, 1:4])


def open_helipr(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                **options) -> Sequence:
    """Open one HeLiPR sensor folder, ``<seq>/LiDAR/<Sensor>``."""
    check_options("helipr", {**options, **({"calib": calib} if calib else {})})
    sensor = helipr_sensor(path)
    if sensor is None:
        raise LirisError(path, f"open a HeLiPR sensor folder <seq>/LiDAR/<Sensor>, Sensor one of "
                               f"{', '.join(HELIPR_SENSORS)}")
    seq_dir = path.parent.parent
    scans = list_files(path, ".bin", f"HeLiPR {sensor} scan")
    stamps = stem_stamps(scans, path)
    pose_path = Path(poses) if poses is not None else (
        seq_dir / "LiDAR_GT" / f"global_{sensor}_gt.txt")
    if not pose_path.is_file():
        raise LirisError(pose_path, f"HeLiPR ground truth not found (expected "
                                    f"LiDAR_GT/global_{sensor}_gt.txt in {seq_dir})")
    gt_ns, gt_poses = read_ground_truth(pose_path)
    keep, matched, dropped = match_scans(ns_to_seconds(stamps, 10**9),
                                         ns_to_seconds(gt_ns, 10**9), gt_poses, tolerance,
                                         pose_path)
    return build("helipr", path, f"{seq_dir.name}-{sensor}", pick(scans, keep), matched,
                 functools.partial(read_helipr_scan, sensor=sensor), SENSOR_PRESETS[sensor],
                 f"{pose_path} ({sensor} frame)", times=ns_to_seconds(stamps[keep], 10**9),
                 unmatched=dropped, frame_ids=keep)


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def helipr_sensor(path: Path) -> str | None:
    """The HeLiPR sensor name when ``path`` is ``<seq>/LiDAR/<Sensor>``, else None."""
    if path.name in HELIPR_SENSORS and path.parent.name == "LiDAR" and path.is_dir():
        return path.name
    return None


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "helipr", "HeLiPR",
        "<seq>/LiDAR/{Ouster,Velodyne,Aeva,Avia} (open the sensor folder); "
        "<seq>/LiDAR_GT/global_<Sensor>_gt.txt",
        "LiDAR frame of that sensor, t (ns) x y z qx qy qz qw",
        "packed records per sensor (26/22/25-or-29/19 B; Aeva 29 B after stamp "
        "1691936557946849179); pose at each scan stamp",
        "os2-128 (Ouster), vlp16 (Velodyne), avia (Avia), none (Aeva)",
        "a sensor folder under LiDAR/",
        lambda p: helipr_sensor(p) is not None, "helipr:open_helipr",
        frame="each sensor's own frame, z up: kept",
        intensity=("Ouster, Velodyne: the f32 intensity field as stored; Avia: u8 reflectivity "
                   "(0..255); Aeva 25 B (up to stamp 1691936557946849179): the f32 reflectivity "
                   "field; Aeva 29 B: the trailing f32 intensity as stored, negative and dB-like "
                   "(about −73..−27 on real files)")),
)
