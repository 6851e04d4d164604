"""Benchmark: stream a ~1 GB ROS bag of VLP-16-sized clouds through liris.

Writes the bag to a temporary folder (under /tmp by default) with rosbags'
writer, then, in fresh subprocesses, (a) only imports liris and rosbags (the
baseline), and (b) opens the bag with ``open_sequence`` and reads every scan.
Each subprocess reports its peak resident memory (``ru_maxrss``); the bag is
deleted afterwards unless ``--keep``.

Usage::

    python scripts/bench_rosbag.py [--size-gb 1.0] [--format rosbag1|mcap|sqlite3]
                                   [--repeat 1] [--tmp /tmp] [--keep]

Bar (issue 9): reading peak memory under 500 MB.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

VLP16_POINTS = 16 * 1800  # 16 rings × 1800 azimuth steps (10 Hz, 0.2°)
POINT_STEP = 32  # x y z _ intensity ring _ time, PCL-aligned like velodyne_pointcloud
LAYOUT = [("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 16, 7), ("ring", 20, 4),
          ("time", 24, 7)]
SCAN_PERIOD_NS = 100_000_000
ODOM_PER_SCAN = 5
T0_NS = 1_600_000_000_000_000_000

READ_CODE = """
import json, resource, sys, time
t = time.perf_counter()
from lidar_iris_eval.io import open_sequence
import lidar_iris_eval.io.rosbag  # noqa: F401  (imports timed apart from opening)
import rosbags.highlevel  # noqa: F401
imported = time.perf_counter() - t
if sys.argv[1] == "baseline":
    out = {"import_s": imported}
else:
    t = time.perf_counter()
    seq = open_sequence(sys.argv[1])
    opened = time.perf_counter() - t
    t = time.perf_counter()
    n_points = 0
    for i in range(len(seq)):
        n_points += len(seq[i])
    out = {"import_s": imported, "open_s": opened, "read_s": time.perf_counter() - t,
           "scans": len(seq), "points": n_points}
out["maxrss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def base_cloud(rng: np.random.Generator) -> np.ndarray:
    """One VLP-16-like scan as structured records (rings × azimuths)."""
    dtype = np.dtype({
        "names": [n for n, _, _ in LAYOUT],
        "formats": ["<u2" if d == 4 else "<f4" for _, _, d in LAYOUT],
        "offsets": [o for _, o, _ in LAYOUT], "itemsize": POINT_STEP,
    })
    rec = np.zeros(VLP16_POINTS, dtype)
    ring = np.arange(VLP16_POINTS) % 16
    azimuth = np.repeat(np.linspace(0, 2 * np.pi, 1800, endpoint=False), 16)
    elevation = np.deg2rad(-15 + 2 * ring)
    distance = rng.uniform(2, 60, VLP16_POINTS)
    rec["x"] = distance * np.cos(elevation) * np.cos(azimuth)
    rec["y"] = distance * np.cos(elevation) * np.sin(azimuth)
    rec["z"] = distance * np.sin(elevation)
    rec["intensity"] = rng.uniform(0, 255, VLP16_POINTS)
    rec["ring"] = ring
    rec["time"] = np.repeat(np.linspace(0, 0.1, 1800, endpoint=False), 16)
    return rec


def write_bag(path: Path, fmt: str, size_bytes: int) -> int:
    """Write clouds (+ 50 Hz odometry) until the payload reaches ``size_bytes``."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    ros1 = fmt == "rosbag1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    t = ts.types
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    if ros1:
        writer = Writer1(path)
    else:
        plugin = StoragePlugin.MCAP if fmt == "mcap" else StoragePlugin.SQLITE3
        writer = Writer2(path, version=9, storage_plugin=plugin)

    def header(ns: int, frame: str):
        stamp = t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        if ros1:
            return t["std_msgs/msg/Header"](seq=0, stamp=stamp, frame_id=frame)
        return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    rng = np.random.default_rng(0)
    rec = base_cloud(rng)
    field = t["sensor_msgs/msg/PointField"]
    fields = [field(name=n, offset=o, datatype=d, count=1) for n, o, d in LAYOUT]
    vec = t["geometry_msgs/msg/Vector3"]
    zero_twist = t["geometry_msgs/msg/TwistWithCovariance"](
        twist=t["geometry_msgs/msg/Twist"](linear=vec(0, 0, 0), angular=vec(0, 0, 0)),
        covariance=np.zeros(36),
    )
    n_scans = max(1, size_bytes // (VLP16_POINTS * POINT_STEP))
    writer.open()
    cloud_conn = writer.add_connection("/velodyne_points", "sensor_msgs/msg/PointCloud2",
                                       typestore=ts)
    odom_conn = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
    for k in range(n_scans):
        stamp = T0_NS + k * SCAN_PERIOD_NS
        rec["x"] += 0.01  # scans differ, so nothing can be deduplicated
        msg = t["sensor_msgs/msg/PointCloud2"](
            header=header(stamp, "velodyne"), height=16, width=1800, fields=fields,
            is_bigendian=False, point_step=POINT_STEP, row_step=1800 * POINT_STEP,
            data=rec.view(np.uint8), is_dense=True,
        )
        writer.write(cloud_conn, stamp, serialize(msg, msg.__msgtype__))
        for j in range(ODOM_PER_SCAN):
            ns = stamp + j * SCAN_PERIOD_NS // ODOM_PER_SCAN
            pose = t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=ns / 1e9 - 1.6e9, y=0.0, z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            )
            odom = t["nav_msgs/msg/Odometry"](
                header=header(ns, "odom"), child_frame_id="velodyne",
                pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose,
                                                               covariance=np.zeros(36)),
                twist=zero_twist,
            )
            writer.write(odom_conn, ns, serialize(odom, odom.__msgtype__))
    writer.close()
    return n_scans


def run_reader(target: str) -> dict:
    out = subprocess.run([sys.executable, "-c", READ_CODE, target], check=True,
                         capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def disk_size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size-gb", type=float, default=1.0)
    parser.add_argument("--format", choices=["rosbag1", "mcap", "sqlite3"], default="rosbag1")
    parser.add_argument("--repeat", type=int, default=1, help="read runs (median reported)")
    parser.add_argument("--tmp", default="/tmp")
    parser.add_argument("--keep", action="store_true", help="do not delete the bag")
    args = parser.parse_args()

    folder = Path(tempfile.mkdtemp(prefix="liris_bench_rosbag_", dir=args.tmp))
    bag = folder / ("bench.bag" if args.format == "rosbag1" else "bench")
    try:
        t = time.perf_counter()
        n_scans = write_bag(bag, args.format, int(args.size_gb * 1e9))
        write_s = time.perf_counter() - t
        baseline = run_reader("baseline")
        runs = [run_reader(str(bag)) for _ in range(args.repeat)]
        report = {
            "format": args.format,
            "bag_bytes": disk_size(bag),
            "scans_written": n_scans,
            "points_per_scan": VLP16_POINTS,
            "write_s": round(write_s, 2),
            "baseline_import_maxrss_mb": round(baseline["maxrss_mb"], 1),
            "read_maxrss_mb": round(statistics.median(r["maxrss_mb"] for r in runs), 1),
            "read_minus_baseline_mb": round(
                statistics.median(r["maxrss_mb"] for r in runs) - baseline["maxrss_mb"], 1),
            "open_s_median": round(statistics.median(r["open_s"] for r in runs), 2),
            "read_all_s_median": round(statistics.median(r["read_s"] for r in runs), 2),
            "scans_read": runs[0]["scans"],
            "points_read": runs[0]["points"],
            "repeats": args.repeat,
            "bar_maxrss_mb": 500,
        }
        report["ms_per_scan"] = round(1000 * report["read_all_s_median"] / max(1, n_scans), 2)
        print(json.dumps(report, indent=2))
    finally:
        if not args.keep:
            shutil.rmtree(folder, ignore_errors=True)
        else:
            print(f"kept {bag}", file=sys.stderr)


if __name__ == "__main__":
    main()
