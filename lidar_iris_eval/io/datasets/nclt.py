"""NCLT: ``velodyne_sync/<utime>.bin`` scans or the raw ``velodyne_hits.bin``, body-frame poses.

Both formats store a point in 8 bytes: **uint16** x, y, z (metres =
``value · 0.005 − 100``), uint8 intensity, uint8 laser id, little-endian.
Reading the coordinates as int16 (as some loaders do) wraps every coordinate
above about 63.8 m; here they are uint16.

Frame: NCLT's Velodyne frame is z-down (the dataset's ``read_vel_sync.py``
plots ``-z``; the road lies at positive z) and, by the body → Velodyne extrinsic
below (yaw −90.703° in the x-forward, y-right, z-down body frame), its x axis
points left and its y axis forward. liris turns every scan into its x-forward,
y-left, z-up frame (as KITTI) with :data:`TO_LIRIS` (x' = y, y' = x, z' = −z:
a half turn about the horizontal axis between x and y), and the poses with it.

``velodyne_hits.bin`` is a stream of packets: an 8-byte magic (four uint16
44444), a uint32 hit count, a uint64 utime, 4 padding bytes, then the hits.
A scan is one revolution: a new scan starts at the packet whose first hit
crosses the ±180° azimuth (behind the sensor), so the first and last scans of
a recording may be partial turns.

``groundtruth_<date>.csv``: utime (µs), x, y, z, roll, pitch, yaw (radians)
of the *body* frame (rows with NaN are skipped). Each scan gets the pose at
its stamp (within :data:`TOLERANCE`), then ``T_body · T_body_velodyne`` with
NCLT's body → Velodyne extrinsic (x, y, z, roll, pitch, yaw =
0.002, −0.004, −0.957 m, 0.807°, 0.166°, −90.703°; rotation Rz·Ry·Rx).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.datasets.base import (
    build,
    check_options,
    finite_rows,
    list_files,
    match_scans,
    pick,
    read_records,
    read_table,
    record_dtype,
    rpy_zyx,
    se3,
    stem_stamps,
)
from lidar_iris_eval.io.datasets.spec import DatasetSpec, has_dir, has_file
from lidar_iris_eval.io.scans import Scan, clean_points
from lidar_iris_eval.io.sequence import Sequence

SCALE = 0.005
OFFSET = -100.0
POINT = record_dtype([("x", "<u2"), ("y", "<u2"), ("z", "<u2"), ("intensity", "u1"),
                      ("laser_id", "u1")])
PACKET_MAGIC = 44444
PACKET_HEADER_BYTES = 24  # 4 x uint16 magic, uint32 count, uint64 utime, 4 padding
#: body -> Velodyne: metres and degrees (x, y, z, roll, pitch, yaw)
BODY_TO_VELODYNE = (0.002, -0.004, -0.957, 0.807, 0.166, -90.703)
#: NCLT's Velodyne frame (x left, y forward, z down) -> liris's (x forward, y left, z up)
TO_LIRIS = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
#: seconds between a scan stamp and the nearest ground-truth sample
TOLERANCE = 0.1


def decode(records: np.ndarray, source: Path) -> Scan:
    """Points (m) and intensity of NCLT hit records (uint16 coordinates)."""
    xyz = np.stack([records["x"], records["y"], records["z"]], axis=1).astype(np.float64)
    return clean_points((xyz * SCALE + OFFSET).astype(np.float32),
                        records["intensity"].astype(np.float32), source)


def read_sync_scan(path: Path) -> Scan:
    """One ``velodyne_sync/<utime>.bin`` scan."""
    return decode(read_records(path, POINT, "NCLT velodyne_sync"), path)


def body_to_velodyne() -> np.ndarray:
    x, y, z, roll, pitch, yaw = BODY_TO_VELODYNE
    return se3(rpy_zyx(*np.radians([roll, pitch, yaw]))[0], (x, y, z))


def find_ground_truth(session: Path) -> Path:
    """``groundtruth_<date>.csv`` in the session folder, beside it, or in ``ground_truth/``."""
    name = f"groundtruth_{session.name}.csv"
    places = [session, session.parent, session.parent / "ground_truth",
              session.parent.parent / "ground_truth"]
    for place in places:
        if (place / name).is_file():
            return place / name
    raise LirisError(session, f"NCLT ground truth not found: looked for {name} in "
                              f"{', '.join(str(p) for p in places)}; give it with --poses")


def read_ground_truth(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """``(seconds (M,), Velodyne-frame poses (M, 4, 4))`` from a ground-truth csv."""
    table = finite_rows(read_table(path, 7, "NCLT ground truth", nonfinite_ok=True), path,
                        "ground-truth")
    body = se3(rpy_zyx(table[:, 4], table[:, 5], table[:, 6]), table[:, 1:4])
    return table[:, 0] * 1e-6, body @ body_to_velodyne()


def _poses_for(session: Path, poses, scan_seconds: np.ndarray, tolerance: float):
    pose_path = Path(poses) if poses is not None else find_ground_truth(session)
    pose_times, lidar = read_ground_truth(pose_path)
    keep, matched, dropped = match_scans(scan_seconds, pose_times, lidar, tolerance, pose_path)
    return pose_path, keep, matched, dropped


def open_nclt_sync(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                   **options) -> Sequence:
    """Open an NCLT session's ``velodyne_sync`` scans (the ``<date>`` folder or the scan folder)."""
    check_options("nclt", {**options, **({"calib": calib} if calib else {})})
    session = nclt_session(path) or (path.parent if path.name == "velodyne_sync" else path)
    scans = list_files(session / "velodyne_sync", ".bin", "NCLT velodyne_sync scan")
    utime = stem_stamps(scans, session / "velodyne_sync")
    pose_path, keep, matched, dropped = _poses_for(session, poses, utime * 1e-6, tolerance)
    return build("nclt", session, session.name, pick(scans, keep), matched, read_sync_scan,
                 "hdl32", f"{pose_path} (body frame) · T_body_velodyne",
                 times=utime[keep] * 1e-6, unmatched=dropped, frame_ids=keep,
                 to_liris=TO_LIRIS)


# --- raw velodyne_hits.bin ---------------------------------------------------------


@functools.lru_cache(maxsize=1)
def _walker():
    try:
        import numba
    except ImportError:  # pragma: no cover - numba is a dependency
        return _walk_packets
    return numba.njit(cache=True, nogil=True)(_walk_packets)


def _walk_packets(data: np.ndarray, out: np.ndarray) -> int:
    """Index the packets of ``data`` (uint8) into ``out`` rows (offset, count, utime, x, y).

    Returns the packet count, or ``-1 - offset`` of a packet with a bad magic,
    or ``-(2**62) - offset`` of a packet cut short by the end of the data.
    """
    n = data.size
    pos = 0
    k = 0
    while pos < n:
        if pos + 24 > n:
            return -(2**62) - pos
        for j in range(4):
            if data[pos + 2 * j] != 0x9C or data[pos + 2 * j + 1] != 0xAD:
                return -1 - pos
        count = 0
        for j in range(4):
            count |= np.int64(data[pos + 8 + j]) << (8 * j)
        utime = 0
        for j in range(8):
            utime |= np.int64(data[pos + 12 + j]) << (8 * j)
        end = pos + 24 + 8 * count
        if end > n:
            return -(2**62) - pos
        x = 0
        y = 0
        if count > 0:
            x = np.int64(data[pos + 24]) | (np.int64(data[pos + 25]) << 8)
            y = np.int64(data[pos + 26]) | (np.int64(data[pos + 27]) << 8)
        out[k, 0] = pos
        out[k, 1] = count
        out[k, 2] = utime
        out[k, 3] = x
        out[k, 4] = y
        k += 1
        pos = end
    return k


def index_packets(data: np.ndarray, source: Path, base: int = 0) -> np.ndarray:
    """``(P, 5)`` int64 rows: byte offset, hit count, utime, first hit's raw x and y."""
    out = np.zeros((data.size // PACKET_HEADER_BYTES + 1, 5), dtype=np.int64)
    status = _walker()(data, out)
    record = (f"{PACKET_HEADER_BYTES}-byte packet header (4 x uint16 {PACKET_MAGIC}, uint32 "
              f"count, uint64 utime, 4 padding) + {POINT.itemsize}-byte hits")
    if status <= -(2**62):
        offset = base + (-(status + 2**62))
        raise LirisError(source, f"truncated NCLT velodyne_hits.bin: the packet at byte {offset} "
                                 f"is cut short (expected a {record})")
    if status < 0:
        offset = base + (-(status + 1))
        raise LirisError(source, f"not an NCLT velodyne_hits.bin packet at byte {offset}: "
                                 f"no magic (expected a {record})")
    return out[:status]


def split_revolutions(packets: np.ndarray) -> list[tuple[int, int]]:
    """``(start byte, end byte)`` of each revolution: a new one where the azimuth wraps."""
    x = packets[:, 3] * SCALE + OFFSET
    y = packets[:, 4] * SCALE + OFFSET
    azimuth = np.where(packets[:, 1] > 0, np.arctan2(y, x), np.nan)
    # a packet without hits has no azimuth: carry the previous one forward
    filled = np.flatnonzero(~np.isnan(azimuth))
    if filled.size:
        last = np.maximum.accumulate(np.where(~np.isnan(azimuth), np.arange(len(azimuth)), 0))
        azimuth = azimuth[last]
        azimuth[np.isnan(azimuth)] = azimuth[filled[0]]
    wraps = np.flatnonzero(np.abs(np.diff(azimuth)) > np.pi) + 1
    starts = np.r_[0, wraps]
    stops = np.r_[wraps, len(packets)]
    ends = packets[:, 0] + PACKET_HEADER_BYTES + POINT.itemsize * packets[:, 1]
    return [(int(packets[a, 0]), int(ends[b - 1])) for a, b in zip(starts, stops, strict=True)
            if packets[a:b, 1].sum() > 0]


def read_hits_scan(path: Path, record: tuple[int, int]) -> Scan:
    """The hits of one revolution, ``record`` = (start byte, end byte) in ``velodyne_hits.bin``."""
    start, stop = record
    with open(path, "rb") as handle:
        handle.seek(start)
        data = np.frombuffer(handle.read(stop - start), dtype=np.uint8)
    if data.size != stop - start:
        raise LirisError(path, f"truncated NCLT velodyne_hits.bin: bytes {start}..{stop} missing")
    packets = index_packets(data, path, base=start)
    offsets = packets[:, 0] + PACKET_HEADER_BYTES
    counts = packets[:, 1] * POINT.itemsize
    run_starts = np.cumsum(counts) - counts
    index = np.repeat(offsets - run_starts, counts) + np.arange(int(counts.sum()))
    return decode(data[index].view(POINT), path)


def open_nclt_hits(path: Path, poses=None, calib=None, tolerance: float = TOLERANCE,
                   **options) -> Sequence:
    """Open an NCLT ``velodyne_hits.bin`` (the file, or the ``<date>`` folder holding it)."""
    check_options("nclt-hits", {**options, **({"calib": calib} if calib else {})})
    hits = nclt_hits_file(path) or path
    if not hits.is_file():
        raise LirisError(hits, "NCLT velodyne_hits.bin not found")
    session = hits.parent
    data = np.memmap(hits, dtype=np.uint8, mode="r") if hits.stat().st_size else np.zeros(0, "u1")
    packets = index_packets(np.asarray(data), hits)
    records = split_revolutions(packets) if len(packets) else []
    if not records:
        raise LirisError(hits, "no hits in the file")
    first = {int(off): int(t) for off, t in zip(packets[:, 0], packets[:, 2], strict=True)}
    utime = np.array([first[start] for start, _ in records], dtype=np.int64)
    pose_path, keep, matched, dropped = _poses_for(session, poses, utime * 1e-6, tolerance)
    return build("nclt-hits", session, session.name, [hits] * len(keep), matched,
                 read_hits_scan, "hdl32", f"{pose_path} (body frame) · T_body_velodyne",
                 times=utime[keep] * 1e-6, unmatched=dropped,
                 records=[records[i] for i in keep], frame_ids=keep, to_liris=TO_LIRIS)


# --- the registry entry: lidar_iris_eval.io.datasets lists SPECS in its order ---------


def nclt_session(path: Path) -> Path | None:
    """The NCLT ``<date>`` folder when ``path`` is it (with velodyne_sync/) or velodyne_sync/."""
    if path.name == "velodyne_sync" and path.is_dir():
        return path.parent
    if has_dir(path, "velodyne_sync"):
        return path
    return None


def nclt_hits_file(path: Path) -> Path | None:
    """``velodyne_hits.bin`` itself, or inside ``path``."""
    if path.name == "velodyne_hits.bin" and path.is_file():
        return path
    if has_file(path, "velodyne_hits.bin"):
        return path / "velodyne_hits.bin"
    return None


#: this module's datasets, in the order `liris datasets` lists them
SPECS: tuple[DatasetSpec, ...] = (
    DatasetSpec(
        "nclt", "NCLT (velodyne_sync)",
        "<date>/velodyne_sync/<utime>.bin; ground_truth/groundtruth_<date>.csv in <date>, "
        "beside it or in ../ground_truth",
        "body frame (z down), utime µs, x y z roll pitch yaw",
        "uint16 coordinates (·0.005 − 100 m, never int16); pose at each scan stamp; "
        "T_body · T_body_velodyne",
        "hdl32", "velodyne_sync/",
        lambda p: nclt_session(p) is not None, "nclt:open_nclt_sync",
        frame=("Velodyne frame x left, y forward, z down → turned to x forward, y left, z up (x' "
               "= y, y' = x, z' = −z); poses turned alike"),
        intensity="the u8 intensity byte (0..255)"),
    DatasetSpec(
        "nclt-hits", "NCLT (raw velodyne_hits.bin)",
        "<date>/velodyne_hits.bin (open the file or <date>); ground truth as for nclt",
        "body frame (z down), utime µs",
        "packets split into revolutions at the ±180° azimuth wrap; as nclt otherwise",
        "hdl32", "velodyne_hits.bin",
        lambda p: nclt_hits_file(p) is not None, "nclt:open_nclt_hits",
        frame="as nclt: turned from x left, y forward, z down to x forward, y left, z up",
        intensity="the u8 intensity byte (0..255)"),
)
