"""ROS 1 (``.bag``) and ROS 2 (``.db3`` / ``.mcap`` / bag folder) recordings.

Read with the pure-Python ``rosbags`` package (optional extra
``lidar_iris_eval[rosbag]``); no ROS installation is needed.

* Scans are ``sensor_msgs/PointCloud2`` messages of one topic (``topic=``, or
  the only point-cloud topic). Fields ``x y z`` and, when present,
  ``intensity``, ``ring`` and ``time`` are decoded with NumPy structured
  dtypes built from the message's own field offsets, so any driver's layout
  (padding, big-endian, row padding) reads.
* Poses come from a ``nav_msgs/Odometry``, ``geometry_msgs/PoseStamped`` or
  ``PoseWithCovarianceStamped`` topic in the bag (``pose_topic=``, or the only
  one), or from a TUM / KITTI pose file (``poses=``). They are taken to be
  poses of the LiDAR itself. Each scan gets the pose interpolated at its
  timestamp (see :mod:`lidar_iris_eval.io.timematch`); scans without a pose
  within ``tolerance`` are dropped with a warning.
* Timestamps are the message header stamps (sensor time) by default;
  ``stamps="bag"`` uses the recording time instead.

Opening a bag makes one streaming pass over the point-cloud messages to index
their times (raw bytes, nothing deserialised, one message in memory at a
time); a scan is read and decoded only when asked for. The reader is reopened
lazily, so the sequence can be pickled to worker processes.
"""

from __future__ import annotations

import hashlib
import os
import struct
from contextlib import contextmanager
from dataclasses import dataclass, field
from itertools import islice
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, options, os_error, warn
from lidar_iris_eval.io.poses import quaternion_to_matrix, read_pose_file
from lidar_iris_eval.io.scans import Scan, clean_points
from lidar_iris_eval.io.sequence import Sequence, hash_file_samples
from lidar_iris_eval.io.timematch import DEFAULT_TOLERANCE, match_poses, select_keyframes

INSTALL_HINT = 'reading ROS bags needs the rosbags package: pip install "lidar_iris_eval[rosbag]"'
CLOUD_TYPE = "sensor_msgs/msg/PointCloud2"
#: pose message type -> attribute path from the message to its geometry_msgs/Pose
POSE_TYPES = {
    "nav_msgs/msg/Odometry": ("pose", "pose"),
    "geometry_msgs/msg/PoseStamped": ("pose",),
    "geometry_msgs/msg/PoseWithCovarianceStamped": ("pose", "pose"),
}
STAMP_SOURCES = ("header", "bag")
#: sensor_msgs/PointField datatype -> NumPy type (byte order added per message)
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
CLOUD_FIELDS = ("x", "y", "z", "intensity", "ring", "time")
NS = 1_000_000_000


@dataclass
class BagSequence(Sequence):
    """A :class:`Sequence` whose scans are messages in a ROS bag.

    ``scan_paths`` is empty (there are no per-scan files); ``frame_ids`` are
    the indices of the kept messages among all messages of ``topic``.
    ``message_times`` (recording time, ns) and ``message_ranks`` locate each
    message for random access.
    """

    topic: str = ""
    message_times: np.ndarray = field(default=None)  # type: ignore[assignment]
    message_ranks: np.ndarray = field(default=None)  # type: ignore[assignment]
    _reader: object = field(default=None, init=False, repr=False, compare=False)
    _reader_pid: int = field(default=0, init=False, repr=False, compare=False)

    def __len__(self) -> int:
        return len(self.poses)

    def scan(self, index: int) -> Scan:
        """Points and intensity of scan ``index`` (NaN points dropped with a warning)."""
        fields = self.scan_fields(index)
        points = np.stack([fields["x"], fields["y"], fields["z"]], axis=1)
        return clean_points(points, fields.get("intensity"), self._source(index))

    def scan_fields(self, index: int) -> dict[str, np.ndarray]:
        """All decoded per-point fields of scan ``index``: x, y, z and, when present,
        intensity, ring and time; unfiltered."""
        if not -len(self) <= index < len(self):
            raise IndexError(f"scan {index} out of range for {len(self)} scans")
        index %= len(self)
        reader = self._open()
        conns = [c for c in reader.connections if c.topic == self.topic]
        stamp = int(self.message_times[index])
        messages = reader.messages(connections=conns, start=stamp, stop=stamp + 1)
        found = next(islice(messages, int(self.message_ranks[index]), None), None)
        if found is None:
            raise LirisError(self._source(index), "message not found (bag changed since opening?)")
        conn, _, raw = found
        with corrupt_bag_errors(self._source(index)):
            msg = reader.deserialize(raw, conn.msgtype)
        return decode_pointcloud2(msg, self._source(index))

    def fingerprint(self) -> str:
        """Hash of the bag files' names, sizes and ends, the topic and the kept messages."""
        digest = hashlib.sha256()
        files = sorted(self.path.iterdir()) if self.path.is_dir() else [self.path]
        hash_file_samples(digest, files)
        digest.update(self.topic.encode())
        digest.update(np.ascontiguousarray(self.message_times, dtype=np.int64).tobytes())
        return digest.hexdigest()[:16]

    def close(self) -> None:
        """Close the bag file (it is reopened if another scan is read)."""
        if self._reader is not None:
            self._reader.close()
            self._reader = None

    def __enter__(self) -> BagSequence:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_reader"] = None  # open files do not pickle; reopen in the worker
        return state

    def _open(self):
        # A reader inherited through fork() shares its file offset with the
        # parent; never use it, open a private one instead.
        if self._reader is None or self._reader_pid != os.getpid():
            self._reader = _open_reader(self.path)
            self._reader_pid = os.getpid()
        return self._reader

    def _source(self, index: int) -> str:
        return f"{self.path}:{self.topic}#{int(self.frame_ids[index])}"


def open_rosbag(
    path: str | Path,
    poses: str | Path | None = None,
    topic: str | None = None,
    pose_topic: str | None = None,
    every: int = 1,
    min_distance: float = 0.0,
    tolerance: float = DEFAULT_TOLERANCE,
    pose_format: str = "auto",
    stamps: str = "header",
    lidar_frame: bool = True,
    **opts,
) -> BagSequence:
    """Open a ROS 1 / ROS 2 recording as a lazily loaded sequence.

    Parameters
    ----------
    path : ``.bag``, ``.db3``, ``.mcap``, or a ROS 2 bag folder with ``metadata.yaml``.
    poses : TUM (timestamped) or KITTI pose file of the LiDAR; instead of a pose topic.
    topic : the PointCloud2 topic; needed only when the bag has several.
    pose_topic : the Odometry / PoseStamped topic; needed only when the bag has several.
    every, min_distance : keyframe selection, see :func:`select_keyframes`.
    tolerance : seconds; scans with no pose sample this close are dropped.
    pose_format : ``"auto"``, ``"tum"`` or ``"kitti"`` for ``poses``.
    stamps : ``"header"`` (message header stamps) or ``"bag"`` (recording time).
    lidar_frame : bag poses are always LiDAR poses; ``False`` is refused.
    """
    path = Path(path)
    if opts:
        raise LirisError(path, f"{options(opts)}: not used for a ROS bag")
    if stamps not in STAMP_SOURCES:
        raise LirisError(f"--stamps {stamps}", f"choose one of {', '.join(STAMP_SOURCES)}")
    if not lidar_frame:
        raise LirisError(path, "poses of a ROS bag are taken as LiDAR poses; no calib is applied")
    if poses is not None and pose_topic is not None:
        raise LirisError("--pose-topic", "give a pose topic or a pose file (--poses), not both")
    reader = _open_reader(path)
    try:
        topics = _topic_types(reader)
        cloud_topic = choose_topic(topics, topic, (CLOUD_TYPE,), "--topic", path)
        cloud_conns = [c for c in reader.connections if c.topic == cloud_topic]
        with corrupt_bag_errors(path):
            log_ns, stamp_ns = index_messages(reader, cloud_conns)
        scan_ns = _pick_stamps(stamp_ns, log_ns, stamps, f"{path}:{cloud_topic}")
        if len(scan_ns) == 0:
            raise LirisError(path, f"topic {cloud_topic} has no messages")
        t0 = int(scan_ns.min())
        if poses is not None:
            pose_times, pose_mats = _pose_file(Path(poses), pose_format, t0)
            source = Path(poses)
        else:
            pose_source = choose_topic(topics, pose_topic, tuple(POSE_TYPES), "--pose-topic", path,
                                       missing_hint="and no pose file was given (--poses)")
            pose_ns, pose_mats = read_pose_topic(reader, pose_source, stamps)
            pose_times = (pose_ns - t0) / NS
            source = f"{path}:{pose_source}"
    finally:
        reader.close()

    scan_times = (scan_ns - t0) / NS
    if pose_times is None:
        if len(pose_mats) != len(scan_ns):
            raise LirisError(
                poses,
                f"{len(pose_mats)} poses without timestamps but {len(scan_ns)} messages on "
                f"{cloud_topic}; use a TUM file (with times) or one pose per message",
            )
        keep, matched = np.arange(len(scan_ns)), pose_mats
    else:
        keep, matched = match_poses(scan_times, pose_times, pose_mats, tolerance, source)
    chosen = select_keyframes(matched[:, :3, 3], every, min_distance)
    keep = keep[chosen]
    return BagSequence(
        name=path.stem if path.is_file() else path.name,
        path=path,
        scan_paths=[],
        poses=matched[chosen],
        camera_poses=None,
        times=scan_ns[keep] // NS + (scan_ns[keep] % NS) / NS,
        calib=None,
        frame_ids=keep,
        topic=cloud_topic,
        message_times=log_ns[keep],
        message_ranks=_duplicate_ranks(log_ns)[keep],
    )


def _open_reader(path: Path):
    try:
        from rosbags.highlevel import AnyReader, AnyReaderError
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise LirisError(path, INSTALL_HINT) from None
    if not path.exists():
        raise LirisError(path, "no such bag")
    try:
        with corrupt_bag_errors(path):
            reader = AnyReader([path], default_typestore=get_typestore(Stores.LATEST))
            reader.open()
    except AnyReaderError as err:
        raise LirisError(path, f"cannot read ROS bag: {err}") from None
    return reader


@contextmanager
def corrupt_bag_errors(path: str | Path):
    """Report what a damaged or foreign file makes the bag library raise as one LirisError.

    ``rosbags`` decodes headers and messages straight from the bytes, so a
    file of random bytes surfaces as ``UnicodeDecodeError``, ``struct.error``,
    ``KeyError``... rather than a bag error. Our own errors pass through, and
    OS errors keep their cause (see :func:`lidar_iris_eval.errors.os_error`).
    """
    try:
        yield
    except LirisError:
        raise
    except OSError as err:
        raise os_error(err, path, "cannot read ROS bag") from None
    except (UnicodeDecodeError, struct.error, KeyError, IndexError, ValueError, EOFError,
            AssertionError, TypeError) as err:
        detail = type(err).__name__
        raise LirisError(path, f"not a readable ROS bag (corrupt or another format: {detail})"
                         ) from None


def _topic_types(reader) -> dict[str, str]:
    """Topic name -> message type (``None`` if the topic mixes types)."""
    return {name: info.msgtype for name, info in reader.topics.items()}


def choose_topic(
    topics: dict[str, str],
    wanted: str | None,
    types: tuple[str, ...],
    option: str,
    path: Path,
    missing_hint: str = "",
) -> str:
    """The requested topic (checked) or the only topic of a supported type."""
    listing = ", ".join(f"{name} ({typ})" for name, typ in sorted(topics.items())) or "none"
    if wanted is not None:
        if wanted not in topics:
            raise LirisError(f"{option} {wanted}", f"no such topic in {path}; topics: {listing}")
        if topics[wanted] not in types:
            raise LirisError(
                f"{option} {wanted}",
                f"unsupported message type {topics[wanted]}; expected {' or '.join(types)}",
            )
        return wanted
    candidates = sorted(name for name, typ in topics.items() if typ in types)
    if len(candidates) == 1:
        return candidates[0]
    kind = " or ".join(types)
    if not candidates:
        hint = f" {missing_hint}" if missing_hint else ""
        raise LirisError(path, f"no {kind} topic{hint}; topics: {listing}")
    raise LirisError(path, f"several {kind} topics {candidates}; choose one with {option}")


def index_messages(reader, conns) -> tuple[np.ndarray, np.ndarray]:
    """Recording times and header stamps (ns) of all messages on ``conns``.

    Streams the raw messages once, parsing only the 8 stamp bytes that open
    every ``std_msgs/Header``; nothing is deserialised or kept.
    """
    log: list[int] = []
    header: list[int] = []
    parse = _cdr_stamp if reader.is2 else _ros1_stamp
    for _, log_time, raw in reader.messages(connections=conns):
        log.append(log_time)
        header.append(parse(raw))
    return np.asarray(log, dtype=np.int64), np.asarray(header, dtype=np.int64)


def _ros1_stamp(raw: bytes) -> int:
    # ROS 1 Header: uint32 seq, uint32 sec, uint32 nsec, string frame_id
    sec, nsec = struct.unpack_from("<II", raw, 4)
    return sec * NS + nsec


def _cdr_stamp(raw: bytes) -> int:
    # CDR: 4-byte encapsulation header (byte 1 = 1 for little-endian), then int32 sec, uint32 ns
    order = "<" if raw[1] == 1 else ">"
    sec, nsec = struct.unpack_from(f"{order}iI", raw, 4)
    return sec * NS + nsec


def _pick_stamps(header: np.ndarray, log: np.ndarray, stamps: str, source: str) -> np.ndarray:
    if stamps == "bag":
        return log
    if len(header) and not np.any(header):
        warn(source, "header stamps are all zero; using recording times (--stamps bag)")
        return log
    return header


def read_pose_topic(reader, topic: str, stamps: str) -> tuple[np.ndarray, np.ndarray]:
    """Times (ns) and ``(M, 4, 4)`` poses from an Odometry / PoseStamped topic."""
    conns = [c for c in reader.connections if c.topic == topic]
    times: list[int] = []
    header: list[int] = []
    rows: list[tuple[float, ...]] = []
    for conn, log_time, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        pose = msg
        for attr in POSE_TYPES[conn.msgtype]:
            pose = getattr(pose, attr)
        p, q = pose.position, pose.orientation
        rows.append((p.x, p.y, p.z, q.x, q.y, q.z, q.w))
        times.append(log_time)
        header.append(msg.header.stamp.sec * NS + msg.header.stamp.nanosec)
    if not rows:
        raise LirisError(f"--pose-topic {topic}", "pose topic has no messages")
    values = np.asarray(rows, dtype=np.float64)
    if np.any(np.linalg.norm(values[:, 3:], axis=1) < 1e-9):
        raise LirisError(f"--pose-topic {topic}", "pose message with a zero quaternion")
    mats = np.tile(np.eye(4), (len(values), 1, 1))
    mats[:, :3, :3] = quaternion_to_matrix(values[:, 3:])
    mats[:, :3, 3] = values[:, :3]
    ns = _pick_stamps(np.asarray(header, np.int64), np.asarray(times, np.int64), stamps, topic)
    return ns, mats


def _pose_file(path: Path, fmt: str, t0_ns: int) -> tuple[np.ndarray | None, np.ndarray]:
    """Pose file times relative to the first scan (seconds), or None for KITTI files."""
    times, mats = read_pose_file(path, fmt)
    if times is None:
        return None, mats
    return (times - t0_ns // NS) - (t0_ns % NS) / NS, mats


def _duplicate_ranks(times: np.ndarray) -> np.ndarray:
    """For each message, how many earlier messages share its recording time."""
    order = np.argsort(times, kind="stable")
    sorted_times = times[order]
    first = np.searchsorted(sorted_times, sorted_times, side="left")
    ranks = np.empty(len(times), dtype=np.int64)
    ranks[order] = np.arange(len(times)) - first
    return ranks


def decode_pointcloud2(msg, source: str | Path = "PointCloud2") -> dict[str, np.ndarray]:
    """Decode a ``sensor_msgs/PointCloud2`` into 1-D arrays per field.

    Uses the message's own ``fields`` (name, offset, datatype), ``point_step``,
    ``row_step`` and ``is_bigendian``; fields other than x, y, z, intensity,
    ring and time are skipped, and rows padded beyond ``width · point_step``
    are cut.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [name for name in ("x", "y", "z") if name not in fields]
    if missing:
        have = list(fields)
        raise LirisError(source, f"PointCloud2 has no {'/'.join(missing)} field; fields: {have}")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for name in CLOUD_FIELDS:
        f = fields.get(name)
        if f is None or f.count != 1:
            continue
        if f.datatype not in POINTFIELD_TYPES:
            raise LirisError(source, f"PointCloud2 field {name!r}: unknown datatype {f.datatype}")
        names.append(name)
        formats.append(np.dtype(POINTFIELD_TYPES[f.datatype]).newbyteorder(order))
        offsets.append(f.offset)
    step = int(msg.point_step)
    ends = [o + t.itemsize for o, t in zip(offsets, formats, strict=True)]
    if step <= 0 or max(ends) > step:
        raise LirisError(source, f"PointCloud2 point_step {step} smaller than its fields")
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": step})
    width, height, row_step = int(msg.width), int(msg.height), int(msg.row_step)
    data = np.asarray(msg.data, dtype=np.uint8)
    row_bytes = width * step
    if row_step < row_bytes or len(data) < row_step * (height - 1) + row_bytes:
        raise LirisError(
            source,
            f"truncated PointCloud2: {len(data)} data bytes for {height}×{width} points "
            f"of {step} bytes (row_step {row_step})",
        )
    if height > 1 and row_step != row_bytes:
        rows = np.lib.stride_tricks.as_strided(data, (height, row_bytes), (row_step, 1))
        data = np.ascontiguousarray(rows).reshape(-1)
    records = np.frombuffer(data[: height * row_bytes].tobytes(), dtype=dtype)
    return {name: records[name] for name in names}
