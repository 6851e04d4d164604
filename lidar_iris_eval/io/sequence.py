"""The :class:`Sequence`: lazily loaded scans with LiDAR-frame poses.

Opening a sequence only lists file names and parses the (small) pose file, so
a 4541-scan KITTI sequence opens instantly; a scan is read when indexed.
"""

from __future__ import annotations

import contextlib
import contextvars
import hashlib
import importlib
from collections.abc import Callable, Iterator
from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, option, warn
from lidar_iris_eval.io.scans import LABEL_SUFFIX, Scan, read_kitti_bin, read_npy, with_labels

#: file suffix -> reader (a callable, or "module:function" imported on first use)
SCAN_READERS: dict[str, Callable[[Path], Scan] | str] = {
    ".bin": read_kitti_bin,
    ".npy": read_npy,
    ".pcd": "lidar_iris_eval.io.pcd:read_pcd",
}

FINGERPRINT_SAMPLE_BYTES = 4096
#: the inputs of a method that reads bare points (``Sequence.read``)
POINTS = frozenset({"points"})


def scan_reader(suffix: str) -> Callable[[Path], Scan]:
    """The reader function for a scan file suffix such as ``.bin``."""
    reader = SCAN_READERS.get(suffix.lower())
    if reader is None:
        raise LirisError(suffix, f"unsupported scan format; supported: {', '.join(SCAN_READERS)}")
    if isinstance(reader, str):
        module_name, func_name = reader.split(":")
        reader = getattr(importlib.import_module(module_name), func_name)
    return reader


@dataclass
class Sequence(SequenceABC):
    """Scans on disk plus one pose per scan.

    Attributes
    ----------
    name : short label used in output (e.g. ``"00"``).
    path : the folder the sequence was opened from.
    scan_paths : one file per scan, in frame order.
    poses : ``(N, 4, 4)`` LiDAR-frame poses.
    camera_poses : ``(N, 4, 4)`` camera-frame poses as given by KITTI, or None.
    times : ``(N,)`` seconds, or None.
    calib : the 4×4 ``Tr`` (Velodyne → camera), or None.
    frame_ids : integer id of each scan (from its file name when numeric).
    label_paths : one SemanticKITTI ``.label`` file per scan, or None when the
        sequence has no labels.
    labels_dir : where labels are (or would be) looked for, for messages
        ("needs labels, none in <labels_dir>"); None when the format has no
        place for them (ROS bags).
    """

    name: str
    path: Path
    scan_paths: list[Path]
    poses: np.ndarray
    camera_poses: np.ndarray | None = None
    times: np.ndarray | None = None
    calib: np.ndarray | None = None
    frame_ids: np.ndarray = field(default=None)  # type: ignore[assignment]
    label_paths: list[Path] | None = None
    labels_dir: Path | None = None

    #: scans of this sequence never carry objects (see io/objects.py for those)
    has_objects = False

    def __post_init__(self) -> None:
        if self.frame_ids is None:
            self.frame_ids = np.array([_frame_id(p, i) for i, p in enumerate(self.scan_paths)])

    def __len__(self) -> int:
        return len(self.scan_paths)

    def __getitem__(self, index: int) -> np.ndarray:  # type: ignore[override]
        """Points ``(N, 3)`` float32 of scan ``index`` (its label file is not read)."""
        return self.read(index, POINTS).points

    def __iter__(self) -> Iterator[np.ndarray]:
        for i in range(len(self)):
            yield self[i]

    @property
    def has_labels(self) -> bool:
        """True when every scan has a per-point label file."""
        return self.label_paths is not None

    @property
    def provides(self) -> frozenset[str]:
        """The inputs a method may ask of this sequence's scans (``Descriptor.inputs``)."""
        base = {"points", "intensity"}
        return frozenset(base | {"labels"} if self.has_labels else base)

    def scan(self, index: int) -> Scan:
        """Points, intensity and (when the sequence has them) labels of scan ``index``."""
        path = self.scan_paths[index]
        reader = scan_reader(path.suffix)
        if self.label_paths is None:
            return reader(path)
        return with_labels(reader, path, self.label_paths[index])

    def read(self, index: int, inputs: frozenset[str] | set[str] = POINTS) -> Scan:
        """Scan ``index`` with what ``inputs`` (``Descriptor.inputs`` names) ask for.

        The label file is read only when ``"labels"`` is asked for (issue 41:
        methods without labels read 2.1 GB less on SemanticKITTI 00); the point
        file gives points and intensity together. Everything else is
        :meth:`scan`, which formats with their own reader override.
        """
        if self.label_paths is None or "labels" in inputs:
            return self.scan(index)
        path = self.scan_paths[index]
        return scan_reader(path.suffix)(path)

    def positions(self, frame: str = "lidar") -> np.ndarray:
        """``(N, 3)`` translations of the LiDAR or camera poses."""
        if frame == "lidar":
            return self.poses[:, :3, 3].copy()
        if frame == "camera":
            if self.camera_poses is None:
                return self.poses[:, :3, 3].copy()
            return self.camera_poses[:, :3, 3].copy()
        raise LirisError(option("pose_frame", frame), "unknown pose frame; choose lidar or camera")

    def resolve_pose_frame(self, frame: str) -> str:
        """The pose frame to use for ground truth, given the one requested.

        ``camera`` falls back to ``lidar`` (with a warning) when the sequence has
        no camera poses, e.g. a ROS bag or a folder with LiDAR-frame poses, so
        output never claims a convention that was not applied.
        """
        if frame == "camera" and self.camera_poses is None:
            warn(self.path, "no camera poses; using LiDAR-frame poses for ground truth")
            return "lidar"
        return frame

    def fingerprint(self) -> str:
        """A content fingerprint of the scans, for cache keys.

        Hashes each file's name, size, modification time and its first and
        last 4 KiB: cheap for thousands of scans. The modification time catches
        an in-place edit that keeps the size and both ends (a copy without
        ``cp -p`` therefore misses the cache once). Inside
        :func:`full_scan_hashing` (``--verify-scans``) every byte is hashed.
        """
        digest = hashlib.sha256()
        hash_file_samples(digest, self.scan_paths)
        return digest.hexdigest()[:16]


_FULL_HASH: contextvars.ContextVar[bool] = contextvars.ContextVar("liris_full_hash",
                                                                  default=False)


@contextlib.contextmanager
def full_scan_hashing(enabled: bool = True) -> Iterator[None]:
    """Within this block, fingerprints hash every byte of every scan file.

    Slow (reads the whole dataset) but catches any change; the cache keys
    differ from sampled fingerprints, so verified results are cached apart.
    """
    token = _FULL_HASH.set(enabled)
    try:
        yield
    finally:
        _FULL_HASH.reset(token)


def hash_file_samples(digest, paths: list[Path]) -> None:
    """Feed each file's name, size, mtime and first and last 4 KiB into ``digest``.

    Inside :func:`full_scan_hashing`, the name, size and every byte instead.
    """
    full = _FULL_HASH.get()
    for path in paths:
        stat = path.stat()
        size = stat.st_size
        if full:
            digest.update(f"{path.name}:{size}:full;".encode())
            with open(path, "rb") as handle:
                for block in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(block)
            continue
        digest.update(f"{path.name}:{size}:{stat.st_mtime_ns};".encode())
        with open(path, "rb") as handle:
            digest.update(handle.read(FINGERPRINT_SAMPLE_BYTES))
            if size > 2 * FINGERPRINT_SAMPLE_BYTES:
                handle.seek(size - FINGERPRINT_SAMPLE_BYTES)
                digest.update(handle.read())


def read_scan(sequence, index: int, inputs: frozenset[str] | set[str]):
    """Scan ``index`` of any sequence, reading only ``inputs`` where it can choose
    (:meth:`Sequence.read`); other sequence objects give their whole ``scan``."""
    if isinstance(sequence, Sequence):
        return sequence.read(index, inputs)
    return sequence.scan(index)


def find_labels(labels_dir: Path, scan_paths: list[Path]) -> list[Path] | None:
    """``labels_dir/<stem>.label`` for every scan, or None when ``labels_dir`` is absent.

    A labels folder that lacks some scans' files is an error naming the first
    missing one: silently evaluating a labelled method on part of a sequence
    would be worse.
    """
    if not labels_dir.is_dir():
        return None
    present = {p.name for p in labels_dir.iterdir()}
    paths = [labels_dir / f"{p.stem}{LABEL_SUFFIX}" for p in scan_paths]
    missing = [p for p in paths if p.name not in present]
    if missing:
        raise LirisError(
            missing[0], f"label file missing ({len(missing)} of {len(paths)} scans have none)"
        )
    return paths


def _frame_id(path: Path, default: int) -> int:
    return int(path.stem) if path.stem.isdigit() else default


def check_counts(scans: int | list[Path], n_rows: int, scans_dir: Path, source,
                 what: str = "poses") -> None:
    """Scan and pose (or time) counts must match; say which files disagree.

    Given the scan paths rather than their count, the message also names the
    first gap in numeric file names (``000117.bin`` missing between its
    neighbours), which is where such a mismatch usually comes from.
    """
    paths = scans if isinstance(scans, list) else None
    n_scans = len(scans) if paths is not None else int(scans)
    if n_scans == n_rows:
        return
    detail = ""
    if paths:
        gap = first_gap(paths)
        if gap is not None:
            detail = f"; no scan numbered {gap} (between {paths[0].name} and {paths[-1].name})"
        else:
            detail = f"; scans {paths[0].name} .. {paths[-1].name}"
    raise LirisError(
        source, f"{n_rows} {what} but {n_scans} scans in {scans_dir}{detail}; counts must be equal"
    )


def first_gap(paths: list[Path]) -> str | None:
    """The first missing number in numeric file names, zero-padded as its neighbours, or None."""
    if not all(p.stem.isdigit() for p in paths):
        return None
    numbers = sorted(int(p.stem) for p in paths)
    for previous, current in zip(numbers[:-1], numbers[1:], strict=True):
        if current > previous + 1:
            return str(previous + 1).zfill(len(paths[0].stem))
    return None


def read_times(path: Path) -> np.ndarray:
    """Scan times in seconds, one number per line (``#`` comments allowed), all finite."""
    if not path.is_file():
        raise LirisError(path, "times file not found")
    try:
        values = np.loadtxt(path, dtype=np.float64, ndmin=1, comments="#")
    except ValueError:
        raise LirisError(path, "malformed times file (one number per line expected)") from None
    if values.ndim != 1:
        raise LirisError(path, "malformed times file (one number per line expected)")
    bad = np.flatnonzero(~np.isfinite(values))
    if len(bad):
        raise LirisError(path, f"time {bad[0] + 1} is {values[bad[0]]} (times must be finite)")
    return values


def scan_entries(folder: Path, wanted: Callable[[Path], bool]) -> list[Path]:
    """Files in ``folder`` whose names ``wanted`` accepts; a dangling link among them is an error.

    ``Path.is_file`` is False for a broken symbolic link and for a link loop,
    so filtering on it would drop such a scan without a word and shift every
    later scan against its pose.
    """
    files = []
    for entry in folder.iterdir():
        if not wanted(entry):
            continue
        if entry.is_file():
            files.append(entry)
        elif entry.is_symlink():
            raise LirisError(entry, "scan is a broken symbolic link or a symbolic-link loop")
    return files


def list_scans(folder: Path) -> list[Path]:
    """Scan files in ``folder`` with a supported suffix, in natural (numeric) order."""
    if not folder.is_dir():
        raise LirisError(folder, "scan folder not found")
    files = scan_entries(folder, lambda p: p.suffix.lower() in SCAN_READERS)
    suffixes = {p.suffix.lower() for p in files}
    if len(suffixes) > 1:
        raise LirisError(folder, f"mixed scan formats {', '.join(sorted(suffixes))}; "
                                 "keep one per folder")
    if not files:
        raise LirisError(folder, f"no scan files ({', '.join(SCAN_READERS)})")
    return sorted(files, key=lambda p: (int(p.stem) if p.stem.isdigit() else float("inf"), p.name))
