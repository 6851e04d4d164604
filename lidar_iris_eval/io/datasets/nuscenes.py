"""nuScenes: ``LIDAR_TOP`` ``*.pcd.bin`` float32 × 5 and the JSON tables, no devkit needed.

The tables (``<dataroot>/v1.0-*/``: ``scene``, ``sample``, ``sample_data``,
``ego_pose``, ``calibrated_sensor``, ``sensor``) are read directly. A sequence
is one scene: its LIDAR_TOP keyframes (``is_key_frame``, 2 Hz), in the order of
the ``next`` tokens from the scene's first sample. A record is x, y, z,
intensity, ring (20 bytes). The LiDAR pose of a keyframe is
``ego_pose · calibrated_sensor`` (global ← ego ← LIDAR_TOP); nuScenes
quaternions are stored (w, x, y, z). Times are µs.

Ego returns: a LIDAR_TOP sweep holds many returns from the car itself (its
roof and body, at elevations down to about −55°). As the devkit does
(``LidarPointCloud.remove_close`` with ``from_file_multisweep``'s
``min_distance`` = 1.0 m), every point with ``|x| < r`` *and* ``|y| < r`` in
the sensor frame is dropped, a 2r × 2r square around the sensor at every
height, r = :data:`EGO_RADIUS`; ``ego_radius=`` of :func:`open_nuscenes`
changes it (0 keeps every point). The LIDAR_TOP frame (x right, y forward, z
up on the car) is z-up already and is kept.

Intensity: the record's fourth float, 0..255 as stored by the devkit.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, read_text
from lidar_iris_eval.io.datasets.base import (
    build,
    check_options,
    quat_xyzw,
    read_records,
    record_dtype,
    se3,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_file
from lidar_iris_eval.io.scans import Scan, clean_points
from lidar_iris_eval.io.sequence import Sequence

POINT = record_dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                      ("ring", "<f4")])
CHANNEL = "LIDAR_TOP"
TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor")
#: metres: points with |x| < r and |y| < r (sensor frame) are the car's own returns and are
#: dropped, as the devkit's ``remove_close(min_distance=1.0)``
EGO_RADIUS = 1.0


def ego_returns(points: np.ndarray, radius: float = EGO_RADIUS) -> np.ndarray:
    """Mask of the points the devkit's ``remove_close(radius)`` drops (``|x|, |y| < radius``)."""
    return (np.abs(points[:, 0]) < radius) & (np.abs(points[:, 1]) < radius)


def read_nuscenes_scan(path: Path, ego_radius: float = EGO_RADIUS) -> Scan:
    """One ``*.pcd.bin`` LiDAR file, without the ego vehicle's returns (:func:`ego_returns`)."""
    data = read_records(path, POINT, "nuScenes .pcd.bin")
    if ego_radius > 0:
        xyz = np.stack([data["x"], data["y"], data["z"]], axis=1)
        data = data[~ego_returns(xyz, ego_radius)]
    return clean_points(np.stack([data["x"], data["y"], data["z"]], axis=1), data["intensity"],
                        path)


def _table(folder: Path, name: str) -> list[dict]:
    path = folder / f"{name}.json"
    if not path.is_file():
        raise LirisError(path, "nuScenes table not found")
    try:
        rows = json.loads(read_text(path, "nuScenes table"))
    except json.JSONDecodeError as err:
        raise LirisError(path, f"not valid JSON ({err.msg} at line {err.lineno})") from None
    if not isinstance(rows, list):
        raise LirisError(path, "nuScenes table must be a JSON list of records")
    return rows


def _pose(record: dict, source: Path) -> np.ndarray:
    try:
        w, x, y, z = record["rotation"]
        return se3(quat_xyzw(np.array([x, y, z, w]), source)[0], record["translation"])
    except (KeyError, ValueError, TypeError):
        raise LirisError(source, f"record {record.get('token')!r} lacks translation/rotation"
                         ) from None


def open_nuscenes(path: Path, poses=None, calib=None, tolerance=None, scene: str | None = None,
                  ego_radius: float = EGO_RADIUS, **options) -> Sequence:
    """Open one scene of a nuScenes data root (``scene=`` names it when there are several).

    ``ego_radius`` (m): half the side of the square around the sensor whose
    points are dropped as the car's own returns (:data:`EGO_RADIUS`; 0 keeps all).
    """
    if not (np.isfinite(ego_radius) and ego_radius >= 0):
        raise LirisError("ego_radius", f"must be a finite number of metres >= 0, not {ego_radius}")
    check_options("nuscenes", {**options, **({"calib": calib} if calib else {}),
                               **({"poses": poses} if poses else {})})
    tables_dir = nuscenes_tables(path)
    if tables_dir is None:
        raise LirisError(path, "no nuScenes tables (v1.0-*/sample_data.json) here")
    root = tables_dir.parent
    t = {name: _table(tables_dir, name) for name in TABLES}
    scenes = t["scene"]
    if scene is None and len(scenes) != 1:
        names = ", ".join(s.get("name", "?") for s in scenes[:5])
        raise LirisError(tables_dir / "scene.json",
                         f"{len(scenes)} scenes ({names}{', ...' if len(scenes) > 5 else ''}); "
                         "choose one with --scene NAME")
    chosen = scenes[0] if scene is None else next(
        (s for s in scenes if s.get("name") == scene), None)
    if chosen is None:
        raise LirisError(f"--scene {scene}", f"no such scene in {tables_dir / 'scene.json'}")
    sensors = {s["token"]: s.get("channel") for s in t["sensor"]}
    calibrated = {c["token"]: c for c in t["calibrated_sensor"]}
    lidar_calib = {tok for tok, c in calibrated.items()
                   if sensors.get(c.get("sensor_token")) == CHANNEL}
    data = {d["token"]: d for d in t["sample_data"]}
    ego = {e["token"]: e for e in t["ego_pose"]}
    start = next((d for d in t["sample_data"]
                  if d.get("sample_token") == chosen.get("first_sample_token")
                  and d.get("calibrated_sensor_token") in lidar_calib), None)
    if start is None:
        raise LirisError(tables_dir / "sample_data.json",
                         f"scene {chosen.get('name')!r} has no {CHANNEL} sample_data")
    files, lidar, times = [], [], []
    record = start
    source = tables_dir / "sample_data.json"
    while record is not None:
        if record.get("is_key_frame"):
            e = ego.get(record.get("ego_pose_token"))
            c = calibrated.get(record.get("calibrated_sensor_token"))
            if e is None or c is None:
                raise LirisError(source, f"sample_data {record['token']!r}: ego_pose or "
                                         "calibrated_sensor token not found")
            files.append(root / record["filename"])
            lidar.append(_pose(e, tables_dir / "ego_pose.json")
                         @ _pose(c, tables_dir / "calibrated_sensor.json"))
            times.append(int(record["timestamp"]) * 1e-6)
        nxt = record.get("next")
        record = data.get(nxt) if nxt else None
    return build("nuscenes", root, str(chosen.get("name", root.name)), files, np.array(lidar),
                 functools.partial(read_nuscenes_scan, ego_radius=float(ego_radius)), "hdl32",
                 f"{tables_dir} (ego_pose · calibrated_sensor)", times=np.array(times),
                 scan_note=f"ego returns |x|,|y| < {float(ego_radius)} m dropped")


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def nuscenes_tables(path: Path) -> Path | None:
    """The ``v1.0-*`` folder of JSON tables under a nuScenes data root, or None."""
    if has_file(path, "sample_data.json") and has_file(path, "ego_pose.json"):
        return path
    if not path.is_dir():
        return None
    for child in sorted(path.glob("v1.0-*")):
        if has_file(child, "sample_data.json"):
            return child
    return None


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "nuscenes", "nuScenes",
        "<dataroot> with v1.0-*/ JSON tables and samples/LIDAR_TOP/*.pcd.bin "
        "(one scene; --scene NAME when there are several)",
        "ego_pose (global) × calibrated_sensor (LIDAR_TOP → ego), µs",
        "keyframes of LIDAR_TOP walked through the next tokens; "
        "pose = ego_pose · calibrated_sensor (quaternions w, x, y, z)",
        "hdl32", "v1.0-*/sample_data.json",
        lambda p: nuscenes_tables(p) is not None, "nuscenes:open_nuscenes",
        frame=("LIDAR_TOP frame (x right, y forward, z up on the car): kept; ego returns dropped "
               "as the devkit does (|x| < 1.0 m and |y| < 1.0 m, remove_close)"),
        intensity="the record's fourth f32 (HDL-32E intensity, 0..255), as stored"),
)
