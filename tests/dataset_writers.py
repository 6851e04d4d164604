"""Tiny datasets written byte for byte in each dataset's own format, for the reader tests.

Every writer takes LiDAR-frame poses (the truth) and scans in the sensor frame,
converts the poses into the dataset's own frame with the extrinsic *as stated
in DATASETS.md*, built here from explicit elementary rotations (not through
the reader's helpers), and writes the files. A test then checks that the
reader returns the scans and the LiDAR poses it was given.

The planted loop: :func:`loop_case` makes five places 20-40 m apart whose
last scan revisits the first (same pose within 0.7 m, same cloud plus noise).
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image
from scipy.spatial.transform import Rotation

# --- explicit rotations ------------------------------------------------------------


def rx(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def ry(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def transform(rotation: np.ndarray, translation) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out


def xyzrpy(x, y, z, roll, pitch, yaw) -> np.ndarray:
    """Rz(yaw) · Ry(pitch) · Rx(roll) with translation (x, y, z)."""
    return transform(rz(yaw) @ ry(pitch) @ rx(roll), (x, y, z))


def rpy_of(rotation: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) with rotation = Rz(yaw) Ry(pitch) Rx(roll)."""
    roll = np.arctan2(rotation[2, 1], rotation[2, 2])
    pitch = -np.arcsin(np.clip(rotation[2, 0], -1, 1))
    yaw = np.arctan2(rotation[1, 0], rotation[0, 0])
    return float(roll), float(pitch), float(yaw)


def quat_of(rotation: np.ndarray) -> np.ndarray:
    """(x, y, z, w)."""
    return Rotation.from_matrix(rotation).as_quat()


# --- the datasets' sensor frames against liris's (x forward, y left, z up) ---------------
#
# The readers rotate z-down frames into liris's; these are the rotations as stated
# in each dataset's tools (rebuilt here from elementary rotations, rounded to the
# exact signed permutation): ``liris = R @ native``.

#: Oxford SDK Velodyne frame: x backward, y left, z down on the car -> half turn about y
OXFORD_TO_LIRIS = np.round(ry(np.pi))
#: NCLT Velodyne frame: x left, y forward, z down -> half turn about (x + y) / sqrt 2
NCLT_TO_LIRIS = np.round(Rotation.from_rotvec(np.pi * np.array([1, 1, 0]) / np.sqrt(2))
                         .as_matrix())


def to_liris_points(points: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=np.float64) @ rotation.T


def to_liris_poses(poses: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """Poses of the native LiDAR frame -> poses of the rotated frame (world points kept)."""
    return np.asarray(poses) @ transform(rotation.T, (0, 0, 0))


# --- the planted loop ------------------------------------------------------------


@dataclass
class Case:
    """Scans (sensor frame), intensities, LiDAR poses and times of a tiny sequence."""

    scans: list[np.ndarray]
    intensity: list[np.ndarray]
    poses: np.ndarray
    times: np.ndarray  # seconds


def place_cloud(rng: np.random.Generator, n_boxes: int = 10, per_box: int = 40,
                far: float = 0.0) -> np.ndarray:
    """A distinctive cloud: random boxes and a ground ring around the sensor."""
    parts = []
    for _ in range(n_boxes):
        r = rng.uniform(4, 30)
        a = rng.uniform(-np.pi, np.pi)
        size = rng.uniform(0.5, 3.0, 3)
        centre = np.array([r * np.cos(a), r * np.sin(a), 0.0])
        box = rng.uniform(-1, 1, (per_box, 3)) * size + centre
        box[:, 2] = rng.uniform(-1.5, size[2] + 1.0, per_box)
        parts.append(box)
    a = rng.uniform(-np.pi, np.pi, 120)
    r = rng.uniform(3, 15, 120)
    parts.append(np.c_[r * np.cos(a), r * np.sin(a), np.full(120, -1.7)])
    if far:
        a = rng.uniform(-np.pi, np.pi, 30)
        parts.append(np.c_[far * np.cos(a), far * np.sin(a), rng.uniform(-1, 3, 30)])
    return np.concatenate(parts)


def loop_case(seed: int = 0, far: float = 0.0, n: int = 5, t0: float = 1_600_000_000.0,
              period: float = 0.1) -> Case:
    """``n`` scans; the last revisits the first (pose within 0.7 m, cloud + 2 cm noise)."""
    rng = np.random.default_rng(seed)
    places = [place_cloud(rng, far=far) for _ in range(n - 1)]
    scans = places + [places[0] + rng.normal(0, 0.02, places[0].shape)]
    intensity = [rng.uniform(0, 100, len(s)) for s in scans]
    xy = [(0, 0), (25, 0), (50, 5), (40, 35), (0.5, 0.4)][:n - 1] + [(0.5, 0.4)]
    yaw = [0.2, 0.5, 1.1, 2.0, 0.2][:n - 1] + [0.2]
    poses = np.array([transform(rz(yw) @ rx(0.01 * i), (x, y, 0.3 * i % 1))
                      for i, ((x, y), yw) in enumerate(zip(xy, yaw, strict=True))])
    times = t0 + period * np.arange(n)
    return Case(scans, intensity, poses, times)


def f32(points: np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=np.float32)


# --- helpers ---------------------------------------------------------------------


def write_pcd(path: Path, points: np.ndarray, intensity: np.ndarray) -> None:
    """A binary PCL PCD with x y z intensity float32."""
    path.parent.mkdir(parents=True, exist_ok=True)
    n = len(points)
    header = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\n"
              f"COUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
              "DATA binary\n")
    body = np.c_[points, intensity].astype("<f4").tobytes()
    path.write_bytes(header.encode() + body)


def kitti_bin(path: Path, points: np.ndarray, intensity: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.c_[points, intensity].astype("<f4").tofile(path)


def rows(path: Path, table, header: str | None = None, fmt: str = "%.17g",
         delimiter: str = ",") -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    text = "" if header is None else header + "\n"
    for row in table:
        text += delimiter.join(v if isinstance(v, str) else fmt % v for v in row) + "\n"
    path.write_text(text)


# --- MulRan ------------------------------------------------------------------------

MULRAN_T_BASE_OUSTER = xyzrpy(1.7042, -0.021, 1.8047, *np.radians([0.0001, 0.0003, 179.6654]))


def write_mulran(root: Path, case: Case, extra_scan: bool = True) -> Path:
    """``<root>/Ouster/<ns>.bin`` and a global_pose.csv at 4x the scan rate (base frame).

    With ``extra_scan`` one more scan lies 5 s after the last pose: unmatched.
    """
    seq = root / "KAIST01"
    ns = [int(round(t * 1e9)) for t in case.times]
    for stamp, pts, inten in zip(ns, case.scans, case.intensity, strict=True):
        kitti_bin(seq / "Ouster" / f"{stamp}.bin", pts, inten)
    if extra_scan:
        kitti_bin(seq / "Ouster" / f"{ns[-1] + 5 * 10**9}.bin", case.scans[1], case.intensity[1])
    table = []
    base = [p @ np.linalg.inv(MULRAN_T_BASE_OUSTER) for p in case.poses]
    for k, (stamp, pose) in enumerate(zip(ns, base, strict=True)):
        table.append([stamp, *pose[:3, :4].ravel()])
        if k + 1 < len(ns):  # rows between scans: poses that must not be picked
            for j in (1, 2, 3):
                odd = pose.copy()
                odd[:3, 3] += 100.0 * j
                table.append([stamp + j * (ns[k + 1] - stamp) // 4, *odd[:3, :4].ravel()])
    table.sort(key=lambda r: r[0])
    rows(seq / "global_pose.csv", [[str(r[0]), *r[1:]] for r in table])
    return seq


# --- NCLT ----------------------------------------------------------------------------

NCLT_T_BODY_VELO = xyzrpy(0.002, -0.004, -0.957, *np.radians([0.807, 0.166, -90.703]))


def nclt_encode(points: np.ndarray, intensity: np.ndarray) -> np.ndarray:
    """8-byte NCLT hits: uint16 (x + 100) / 0.005, uint8 intensity, uint8 laser."""
    raw = np.round((points + 100.0) / 0.005)
    assert raw.min() >= 0 and raw.max() <= 65535
    out = np.zeros(len(points), dtype=[("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("i", "u1"),
                                       ("l", "u1")])
    out["x"], out["y"], out["z"] = raw[:, 0], raw[:, 1], raw[:, 2]
    out["i"] = np.clip(intensity, 0, 255).astype(np.uint8)
    out["l"] = np.arange(len(points)) % 32
    return out


def nclt_decode_expected(encoded: np.ndarray) -> np.ndarray:
    """What the points must read back as (uint16 · 0.005 − 100)."""
    return np.c_[encoded["x"], encoded["y"], encoded["z"]].astype(np.float64) * 0.005 - 100.0


def write_nclt(root: Path, case: Case, hits: bool = False) -> Path:
    """``<root>/2012-01-08/velodyne_sync/<utime>.bin`` (and/or velodyne_hits.bin),
    ``<root>/ground_truth/groundtruth_2012-01-08.csv`` (body frame, a NaN row first)."""
    session = root / "2012-01-08"
    utime = [int(round(t * 1e6)) for t in case.times]
    encoded = [nclt_encode(p, i) for p, i in zip(case.scans, case.intensity, strict=True)]
    for stamp, enc in zip(utime, encoded, strict=True):
        (session / "velodyne_sync").mkdir(parents=True, exist_ok=True)
        enc.tofile(session / "velodyne_sync" / f"{stamp}.bin")
    if hits:
        write_hits(session / "velodyne_hits.bin", utime, case.scans, case.intensity)
    body = [p @ np.linalg.inv(NCLT_T_BODY_VELO) for p in case.poses]
    table = [[utime[0] - 1000, *["nan"] * 6]]
    for stamp, pose in zip(utime, body, strict=True):
        table.append([stamp, *pose[:3, 3], *rpy_of(pose[:3, :3])])
    rows(root / "ground_truth" / "groundtruth_2012-01-08.csv",
         [[str(r[0]), *[v if isinstance(v, str) else float(v) for v in r[1:]]] for r in table])
    return session


def sorted_by_azimuth(points: np.ndarray, intensity: np.ndarray):
    order = np.argsort(np.arctan2(points[:, 1], points[:, 0]), kind="stable")
    return points[order], intensity[order]


def write_hits(path: Path, utime: list[int], scans, intensity, per_packet: int = 50) -> None:
    """Packets: 4 x uint16 44444, uint32 count, uint64 utime, 4 padding, then 8-byte hits.

    Each scan's hits are sorted by azimuth (-180° .. 180°), so a new revolution
    starts where the azimuth wraps, as on the spinning sensor.
    """
    blob = bytearray()
    for stamp, pts, inten in zip(utime, scans, intensity, strict=True):
        pts, inten = sorted_by_azimuth(pts, inten)
        enc = nclt_encode(pts, inten)
        for k, start in enumerate(range(0, len(enc), per_packet)):
            chunk = enc[start:start + per_packet]
            blob += struct.pack("<4HIQ4x", 44444, 44444, 44444, 44444, len(chunk), stamp + k)
            blob += chunk.tobytes()
    path.write_bytes(bytes(blob))


# --- Oxford Radar RobotCar --------------------------------------------------------------

OXFORD_SDK = {"ins": (-1.7132, 0.1181, 1.1948, -0.0125, 0.0400, 0.0050),
              "velodyne_left": (-0.60072, -0.34077, -0.26837, -0.0053948, -0.041998, -3.1337)}


def oxford_ins_to_lidar(ins=OXFORD_SDK["ins"], lidar=OXFORD_SDK["velodyne_left"]) -> np.ndarray:
    return np.linalg.inv(xyzrpy(*ins)) @ xyzrpy(*lidar)


def write_oxford_ins(run: Path, case: Case, ins_to_lidar: np.ndarray) -> None:
    header = ("timestamp,ins_status,latitude,longitude,altitude,northing,easting,down,utm_zone,"
              "velocity_north,velocity_east,velocity_down,roll,pitch,yaw")
    table = []
    for t, pose in zip(case.times, case.poses, strict=True):
        ins = pose @ np.linalg.inv(ins_to_lidar)
        r, p, y = rpy_of(ins[:3, :3])
        table.append([str(int(round(t * 1e6))), "INS_SOLUTION_GOOD", 51.7, -1.2, 100.0,
                      *ins[:3, 3], "30U", 0.0, 0.0, 0.0, r, p, y])
    rows(run / "gps" / "ins.csv", table, header=header)


def write_oxford_bin(root: Path, case: Case) -> Path:
    """Planar (4, N) float32 scans: all x, then y, z, intensity."""
    run = root / "2019-01-10-11-46-21-radar-oxford-10k"
    folder = run / "velodyne_left"
    folder.mkdir(parents=True)
    lines = []
    for t, pts, inten in zip(case.times, case.scans, case.intensity, strict=True):
        stamp = int(round(t * 1e6))
        np.vstack([pts.T, inten]).astype("<f4").tofile(folder / f"{stamp}.bin")
        lines.append(f"{stamp} 1")
    (run / "velodyne_left.timestamps").write_text("\n".join(lines) + "\n")
    write_oxford_ins(run, case, oxford_ins_to_lidar())
    return run


HDL32E = np.array([-0.1862, -0.1628, -0.1396, -0.1164, -0.0930, -0.0698, -0.0466, -0.0232, 0.,
                   0.0232, 0.0466, 0.0698, 0.0930, 0.1164, 0.1396, 0.1628, 0.1862, 0.2094,
                   0.2327, 0.2560, 0.2793, 0.3025, 0.3259, 0.3491, 0.3723, 0.3957, 0.4189,
                   0.4421, 0.4655, 0.4887, 0.5119, 0.5353])


def oxford_raw(rng: np.random.Generator, columns: int = 24):
    """Random raw firings: ranges (32, N) in units of 2 mm, azimuth (N,) in 1/100 deg."""
    ranges = rng.integers(600, 15000, (32, columns)).astype(np.uint16)  # 1.2 .. 30 m
    ranges[rng.random((32, columns)) < 0.1] = 0  # no return
    ranges[0, 0] = 400  # 0.8 m: under the 1 m minimum, dropped
    azimuth = np.sort(rng.integers(0, 36000, columns)).astype(np.uint16)
    intensity = rng.integers(1, 255, (32, columns)).astype(np.uint8)
    return ranges, azimuth, intensity


def oxford_png_bytes(ranges, azimuth, intensity, stamp: int) -> np.ndarray:
    """The 106 x N grey image: intensity, range bytes (LE), azimuth bytes, int64 stamps."""
    n = ranges.shape[1]
    image = np.zeros((106, n), dtype=np.uint8)
    image[0:32] = intensity
    image[32:96] = np.ascontiguousarray(ranges.T, dtype="<u2").view(np.uint8).reshape(n, 64).T
    image[96:98] = azimuth.astype("<u2").view(np.uint8).reshape(n, 2).T
    stamps = np.full(n, stamp, dtype="<i8")
    image[98:106] = stamps.view(np.uint8).reshape(n, 8).T
    return image


def oxford_raw_expected(ranges, azimuth, intensity):
    """Points and intensity the SDK formulas give (ranges > 1 m only)."""
    r = ranges.astype(np.float64) * 0.002
    a = azimuth.astype(np.float64) * (2 * np.pi / 36000)
    points, values = [], []
    for k in range(32):
        for j in range(ranges.shape[1]):
            if r[k, j] > 1.0:
                e = HDL32E[k]
                planar = np.cos(e) * r[k, j]
                points.append((np.sin(a[j]) * planar, -np.cos(a[j]) * planar,
                               np.sin(e) * r[k, j] - 0.090805))
                values.append(intensity[k, j])
    return np.array(points), np.array(values, dtype=float)


def write_oxford_png(root: Path, case: Case, seed: int = 5):
    """Raw .png scans; the last one repeats the first (the planted loop). Returns (run, raws)."""
    rng = np.random.default_rng(seed)
    run = root / "2019-01-10-12-32-52-radar-oxford-10k"
    folder = run / "velodyne_left"
    folder.mkdir(parents=True)
    raws = [oxford_raw(rng, columns=60) for _ in range(len(case.times) - 1)]
    raws.append(raws[0])
    for t, raw in zip(case.times, raws, strict=True):
        stamp = int(round(t * 1e6))
        Image.fromarray(oxford_png_bytes(*raw, stamp), mode="L").save(folder / f"{stamp}.png")
    (run / "velodyne_left.timestamps").write_text(
        "".join(f"{int(round(t * 1e6))} 1\n" for t in case.times))
    write_oxford_ins(run, case, oxford_ins_to_lidar())
    return run, raws


# --- HeLiPR ----------------------------------------------------------------------------

HELIPR_SWITCH = 1691936557946849179
HELIPR_DTYPES = {
    "Ouster": [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"), ("t", "<u4"),
               ("reflectivity", "<u2"), ("ring", "<u2"), ("ambient", "<u2")],
    "Velodyne": [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("intensity", "<f4"),
                 ("ring", "<u2"), ("time", "<f4")],
    "Aeva25": [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("reflectivity", "<f4"),
               ("velocity", "<f4"), ("time_offset", "<i4"), ("line_index", "u1")],
    "Aeva29": [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("reflectivity", "<f4"),
               ("velocity", "<f4"), ("time_offset", "<i4"), ("line_index", "u1"),
               ("intensity", "<f4")],
    "Avia": [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("reflectivity", "u1"), ("tag", "u1"),
             ("line", "u1"), ("offset_time", "<u4")],
}
HELIPR_SIZES = {"Ouster": 26, "Velodyne": 22, "Aeva25": 25, "Aeva29": 29, "Avia": 19}


def helipr_layout(sensor: str, stamp: int) -> str:
    if sensor == "Aeva":
        return "Aeva29" if stamp > HELIPR_SWITCH else "Aeva25"
    return sensor


def write_helipr(root: Path, case: Case, sensor: str, stamps: list[int] | None = None) -> Path:
    """``<seq>/LiDAR/<sensor>/<ns>.bin`` and ``<seq>/LiDAR_GT/global_<sensor>_gt.txt``."""
    seq = root / "Roundabout01"
    folder = seq / "LiDAR" / sensor
    folder.mkdir(parents=True)
    if stamps is None:
        stamps = [int(round(t * 1e9)) for t in case.times]
    for stamp, pts, inten in zip(stamps, case.scans, case.intensity, strict=True):
        layout = helipr_layout(sensor, stamp)
        dtype = np.dtype(HELIPR_DTYPES[layout])
        assert dtype.itemsize == HELIPR_SIZES[layout]
        rec = np.zeros(len(pts), dtype=dtype)
        rec["x"], rec["y"], rec["z"] = pts.T
        for name in dtype.names[3:]:
            if name == "intensity":
                rec[name] = inten
            elif name == "reflectivity":
                rec[name] = np.clip(inten, 0, 255) if dtype[name].kind == "u" else inten + 0.5
            else:
                rec[name] = np.arange(len(pts)) % 7
        rec.tofile(folder / f"{stamp}.bin")
    table = [[str(s), *p[:3, 3], *quat_of(p[:3, :3])] for s, p in
             zip(stamps, case.poses, strict=True)]
    rows(seq / "LiDAR_GT" / f"global_{sensor}_gt.txt", table, delimiter=" ")
    return folder


# --- Wild-Places ---------------------------------------------------------------------------


def write_wild_v3(root: Path, case: Case) -> Path:
    seq = root / "V-03"
    for t, pts, inten in zip(case.times, case.scans, case.intensity, strict=True):
        kitti_bin(seq / "Clouds_downsampled" / f"{t:.6f}.bin", pts, inten)
    table = [[t, *p[:3, 3], *quat_of(p[:3, :3])] for t, p in
             zip(case.times, case.poses, strict=True)]
    rows(seq / "submap_poses.csv", table, header="%time,x,y,z,qx,qy,qz,qw")
    return seq


def write_wild_v12(root: Path, case: Case) -> Path:
    seq = root / "K-02"
    for t, pts, inten in zip(case.times, case.scans, case.intensity, strict=True):
        write_pcd(seq / "Clouds" / f"{t:.6f}.pcd", pts, inten)
    table = [[t, *p[:3, 3], *quat_of(p[:3, :3])] for t, p in
             zip(case.times, case.poses, strict=True)]
    rows(seq / "poses_aligned.csv", table, header="timestamp,x,y,z,qx,qy,qz,qw")
    return seq


# --- Newer College ---------------------------------------------------------------------------

NCD_T_CL = transform(Rotation.from_quat([0, 0, 0.924, 0.383]).as_matrix(), (-0.084, -0.025, 0.05))


def write_newer_college(root: Path, case: Case) -> Path:
    seq = root / "01_short_experiment"
    table = []
    for t, pts, inten, pose in zip(case.times, case.scans, case.intensity, case.poses,
                                   strict=True):
        sec = int(t)
        nsec = int(round((t - sec) * 1e9))
        write_pcd(seq / "raw_format" / "ouster_scan" / f"cloud_{sec}_{nsec:09d}.pcd", pts, inten)
        base = pose @ np.linalg.inv(NCD_T_CL)
        table.append([str(sec), str(nsec), *base[:3, 3], *quat_of(base[:3, :3])])
    rows(seq / "ground_truth" / "registered_poses.csv", table,
         header="# sec,nsec,x,y,z,qx,qy,qz,qw")
    return seq


# --- nuScenes ----------------------------------------------------------------------------------

NUSC_EGO_LIDAR = transform(rz(-np.pi / 2) @ rx(0.01), (0.94, 0.0, 1.84))


def _wxyz(rotation: np.ndarray) -> list[float]:
    x, y, z, w = quat_of(rotation)
    return [float(w), float(x), float(y), float(z)]


def write_nuscenes(root: Path, case: Case, sweeps: int = 2) -> Path:
    """``v1.0-mini`` tables and ``samples|sweeps/LIDAR_TOP`` files for one scene (+ an empty
    second scene); ``sweeps`` non-key frames between keyframes must be skipped."""
    tables = root / "v1.0-mini"
    tables.mkdir(parents=True)
    sensor = [{"token": "s-lidar", "channel": "LIDAR_TOP", "modality": "lidar"},
              {"token": "s-cam", "channel": "CAM_FRONT", "modality": "camera"}]
    calibrated = [{"token": "c-lidar", "sensor_token": "s-lidar",
                   "translation": list(NUSC_EGO_LIDAR[:3, 3]),
                   "rotation": _wxyz(NUSC_EGO_LIDAR[:3, :3]), "camera_intrinsic": []},
                  {"token": "c-cam", "sensor_token": "s-cam", "translation": [0, 0, 0],
                   "rotation": [1, 0, 0, 0], "camera_intrinsic": []}]
    samples, data, ego = [], [], []
    chain = []
    rng = np.random.default_rng(3)
    for k, (t, pts, inten, pose) in enumerate(zip(case.times, case.scans, case.intensity,
                                                  case.poses, strict=True)):
        stamp = int(round(t * 1e6))
        samples.append({"token": f"sample{k}", "timestamp": stamp, "scene_token": "scene-a",
                        "prev": f"sample{k - 1}" if k else "",
                        "next": f"sample{k + 1}" if k + 1 < len(case.times) else ""})
        egop = pose @ np.linalg.inv(NUSC_EGO_LIDAR)
        ego.append({"token": f"ego{k}", "timestamp": stamp, "translation": list(egop[:3, 3]),
                    "rotation": _wxyz(egop[:3, :3])})
        name = f"samples/LIDAR_TOP/n008__LIDAR_TOP__{stamp}.pcd.bin"
        chain.append({"token": f"sd{k}", "sample_token": f"sample{k}", "ego_pose_token": f"ego{k}",
                      "calibrated_sensor_token": "c-lidar", "timestamp": stamp,
                      "fileformat": "pcd", "is_key_frame": True, "filename": name})
        np.c_[pts, inten, np.arange(len(pts)) % 32].astype("<f4").tofile(
            _mk(root / name))
        if k + 1 < len(case.times):
            for j in range(sweeps):
                sweep_stamp = stamp + (j + 1) * 1000
                sname = f"sweeps/LIDAR_TOP/n008__LIDAR_TOP__{sweep_stamp}.pcd.bin"
                ego.append({"token": f"ego{k}s{j}", "timestamp": sweep_stamp,
                            "translation": [999.0, 0, 0], "rotation": [1, 0, 0, 0]})
                chain.append({"token": f"sd{k}s{j}", "sample_token": f"sample{k + 1}",
                              "ego_pose_token": f"ego{k}s{j}",
                              "calibrated_sensor_token": "c-lidar", "timestamp": sweep_stamp,
                              "fileformat": "pcd", "is_key_frame": False, "filename": sname})
                rng.normal(size=(30, 5)).astype("<f4").tofile(_mk(root / sname))
    for prev, cur in zip([None, *chain], chain, strict=False):
        cur["prev"] = prev["token"] if prev else ""
    for cur, nxt in zip(chain, [*chain[1:], None], strict=True):
        cur["next"] = nxt["token"] if nxt else ""
    # a camera sample_data of the first sample, which must be ignored
    data = [{"token": "cam0", "sample_token": "sample0", "ego_pose_token": "ego0",
             "calibrated_sensor_token": "c-cam", "timestamp": 0, "fileformat": "jpg",
             "is_key_frame": True, "filename": "samples/CAM_FRONT/x.jpg", "prev": "",
             "next": ""}, *chain]
    scenes = [{"token": "scene-a", "name": "scene-0061", "first_sample_token": "sample0",
               "last_sample_token": f"sample{len(case.times) - 1}",
               "nbr_samples": len(case.times)},
              {"token": "scene-b", "name": "scene-0103", "first_sample_token": "nosuch",
               "last_sample_token": "nosuch", "nbr_samples": 0}]
    for name, table in {"scene": scenes, "sample": samples, "sample_data": data,
                        "ego_pose": ego, "calibrated_sensor": calibrated,
                        "sensor": sensor}.items():
        (tables / f"{name}.json").write_text(json.dumps(table))
    return root


def _mk(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


# --- Boreas ------------------------------------------------------------------------------------


def pyboreas_angles(rotation: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, yaw) with rotation = roll(r) @ pitch(p) @ yaw(y), pyboreas' passive
    elementary rotations, i.e. rotation.T = Rz(y) Ry(p) Rx(r)."""
    return rpy_of(rotation.T)


def write_boreas(root: Path, case: Case) -> Path:
    seq = root / "boreas-2021-09-02-11-42"
    header = "GPSTime,x,y,z,vx,vy,vz,roll,pitch,yaw,wz,wy,wx"
    table = []
    for t, pts, inten, pose in zip(case.times, case.scans, case.intensity, case.poses,
                                   strict=True):
        stamp = int(round(t * 1e6))
        rec = np.c_[pts, inten, np.arange(len(pts)) % 128, np.linspace(0, 0.1, len(pts))]
        rec.astype("<f4").tofile(_mk(seq / "lidar" / f"{stamp}.bin"))
        r, p, y = pyboreas_angles(pose[:3, :3])
        table.append([str(stamp), *pose[:3, 3], 0, 0, 0, r, p, y, 0, 0, 0])
    rows(seq / "applanix" / "lidar_poses.csv", table, header=header)
    return seq


# --- Apollo-SouthBay -------------------------------------------------------------------------


def write_apollo(root: Path, case: Case) -> Path:
    """``pcds/<n>.pcd`` from 1, pose rows shuffled by index, plus a pcd with no pose row."""
    seq = root / "TestData" / "HighWay237" / "2018-10-12"
    table = []
    for k, (t, pts, inten, pose) in enumerate(zip(case.times, case.scans, case.intensity,
                                                  case.poses, strict=True), start=1):
        write_pcd(seq / "pcds" / f"{k}.pcd", pts, inten)
        table.append([str(k), t, *pose[:3, 3], *quat_of(pose[:3, :3])])
    write_pcd(seq / "pcds" / f"{len(case.times) + 1}.pcd", case.scans[1], case.intensity[1])
    table = table[::-1]
    rows(seq / "poses" / "gt_poses.txt", table, delimiter=" ")
    return seq


# --- KITTI-360 ------------------------------------------------------------------------------------

K360_CAM0_TO_POSE = xyzrpy(1.5, -0.1, 0.9, -np.pi / 2 + 0.01, 0.02, -np.pi / 2)
K360_CAM_TO_VELO = xyzrpy(0.0, -0.08, -0.27, np.pi / 2, -np.pi / 2, 0.0)


def write_kitti360(root: Path, case: Case) -> tuple[Path, np.ndarray, np.ndarray]:
    """Frames 0..n+1; poses only for frames 1, 2, 4, .., n (frame 3 interpolated; 0 and n+1
    outside the posed range). Returns (drive, kept frames, expected LiDAR poses).

    ``case`` gives the LiDAR poses of the posed frames 1, 2, 4, ..; frame 3's
    expected pose is the midpoint of 2 and 4 (linear + half the relative rotation).
    """
    drive = root / "KITTI-360" / "data_3d_raw" / "2013_05_28_drive_0009_sync"
    data = drive / "velodyne_points" / "data"
    velo_to_imu = K360_CAM0_TO_POSE @ np.linalg.inv(K360_CAM_TO_VELO)
    n = len(case.times)
    posed = [1, 2, *range(4, n + 2)]  # n posed frames
    assert len(posed) == n
    imu = {f: case.poses[k] @ np.linalg.inv(velo_to_imu) for k, f in enumerate(posed)}
    scans = {f: (case.scans[k], case.intensity[k]) for k, f in enumerate(posed)}
    rng = np.random.default_rng(11)
    frames = list(range(0, n + 3))
    for f in frames:
        if f in scans:
            kitti_bin(data / f"{f:010d}.bin", *scans[f])
        else:  # an unposed or interpolated frame: a place of its own
            cloud = place_cloud(rng)
            kitti_bin(data / f"{f:010d}.bin", cloud, np.zeros(len(cloud)))
    stamps = [f"2013-05-28 08:46:{2 + f // 10:02d}.{(f % 10) * 100000000 + 826908:09d}"
              for f in frames]
    (drive / "velodyne_points" / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    rows(root / "KITTI-360" / "data_poses" / drive.name / "poses.txt",
         [[str(f), *imu[f][:3, :4].ravel()] for f in posed], delimiter=" ")
    calib = root / "KITTI-360" / "calibration"
    calib.mkdir(parents=True)
    line = " ".join(f"{v:.17g}" for v in K360_CAM0_TO_POSE[:3, :4].ravel())
    (calib / "calib_cam_to_pose.txt").write_text(f"image_00: {line}\nimage_01: {line}\n")
    (calib / "calib_cam_to_velo.txt").write_text(
        " ".join(f"{v:.17g}" for v in K360_CAM_TO_VELO[:3, :4].ravel()) + "\n")
    # expected: frames 1..n+1 kept; frame 3 halfway between frames 2 and 4 (IMU frame)
    a, b = imu[2], imu[4]
    half = Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).as_rotvec() / 2
    mid = transform(a[:3, :3] @ Rotation.from_rotvec(half).as_matrix(), (a[:3, 3] + b[:3, 3]) / 2)
    imu[3] = mid
    kept = np.arange(1, n + 2)
    expected = np.array([imu[f] @ velo_to_imu for f in kept])
    return drive, kept, expected
