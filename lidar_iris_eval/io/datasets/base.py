"""What every dataset reader shares: the sequence type, packed records, frames, time matching.

A dataset reader lists its scan files, reads its pose file, converts the poses
to the LiDAR frame with the dataset's documented extrinsic, and pairs scans
with poses by timestamp through :func:`match_scans` (the same interpolation
and tolerance rule as scan folders and ROS bags, see
:mod:`lidar_iris_eval.io.timematch`). It returns a :class:`DatasetSequence`:
a :class:`~lidar_iris_eval.io.sequence.Sequence` whose scans are read by the
dataset's own record reader instead of by file suffix.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# scipy.spatial.transform is imported where a rotation is built: every reader module imports
# this one when `liris` starts (their SPECS), and scipy's import is most of that start
from lidar_iris_eval.errors import LirisError, read_text
from lidar_iris_eval.io.poses import check_finite, is_number
from lidar_iris_eval.io.scans import Scan
from lidar_iris_eval.io.sequence import Sequence, hash_file_samples, scan_entries
from lidar_iris_eval.io.timematch import match_poses

#: options every dataset reader accepts (besides poses=, which names its own pose file)
COMMON_OPTIONS = ("tolerance",)


@dataclass
class DatasetSequence(Sequence):
    """A sequence of one registered dataset.

    Attributes (besides :class:`~lidar_iris_eval.io.sequence.Sequence`'s)
    ----------
    reader : reads one scan: ``reader(path)``, or ``reader(path, record)`` when
        ``records`` is given (several scans in one file).
    records : one locator per scan inside its file, or None.
    dataset : the registry name (``"mulran"``).
    sensor_preset : the ``--sensor`` preset of the dataset's LiDAR, or None.
    pose_source : the pose file and the conversion applied, for messages.
    unmatched : scans dropped because no pose was within the tolerance.
    to_liris : ``(3, 3)`` rotation from the dataset's sensor frame to liris's
        (x forward, y left, z up, as KITTI), applied to every scan read; the
        poses are already those of the rotated frame (see :func:`build`).
        None where the dataset's frame is already z-up.
    scan_note : what the reader does to the points beyond decoding them (frame
        rotation, ego-return removal), hashed into :meth:`fingerprint`.
    """

    reader: Callable[..., Scan] | None = None
    records: list | None = None
    dataset: str = ""
    sensor_preset: str | None = None
    pose_source: str = ""
    unmatched: int = 0
    to_liris: np.ndarray | None = None
    scan_note: str = ""

    def scan(self, index: int) -> Scan:
        """Points (sensor frame, z up) and intensity of scan ``index``."""
        if self.reader is None:
            return super().scan(index)
        if self.records is None:
            scan = self.reader(self.scan_paths[index])
        else:
            scan = self.reader(self.scan_paths[index], self.records[index])
        if self.to_liris is None:
            return scan
        return scan._replace(points=rotate_points(scan.points, self.to_liris))

    def fingerprint(self) -> str:
        """Sampled hash of each distinct scan file, plus the per-scan records."""
        digest = hashlib.sha256()
        unique = list(dict.fromkeys(self.scan_paths))
        hash_file_samples(digest, unique)
        if self.records is not None:
            digest.update(repr(self.records).encode())
        digest.update(self.dataset.encode())
        digest.update(self.scan_note.encode())
        return digest.hexdigest()[:16]


def rotate_points(points: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``points @ rotation.T`` as float32; exact for the axis flips and swaps used here."""
    rotation = np.asarray(rotation)
    if np.all(np.isin(rotation, (-1.0, 0.0, 1.0))):  # a signed permutation: no rounding
        out = np.empty_like(points, dtype=np.float32)
        for row in range(3):
            col = int(np.flatnonzero(rotation[row])[0])
            out[:, row] = points[:, col] * np.float32(rotation[row, col])
        return out
    return (np.asarray(points, np.float64) @ rotation.T).astype(np.float32)


# --- options ------------------------------------------------------------------


def check_options(dataset: str, options: dict, allowed: Iterable[str] = ()) -> None:
    """Reject reader options that this dataset does not use, naming them."""
    from lidar_iris_eval.errors import options as option_names

    unused = set(options) - set(allowed) - set(COMMON_OPTIONS)
    if unused:
        raise LirisError(option_names(unused), f"not used for dataset {dataset}")


# --- packed binary records ----------------------------------------------------

_KIND = {"f": "f", "u": "u", "i": "i"}


def describe_dtype(dtype: np.dtype) -> str:
    """``"f32 x, f32 y, u16 ring"``: a record layout in words, for error messages."""
    parts = []
    for name in dtype.names:
        field = dtype.fields[name][0]
        parts.append(f"{_KIND.get(field.kind, field.kind)}{8 * field.itemsize} {name}")
    return ", ".join(parts)


def read_records(path: Path, dtype: np.dtype, what: str) -> np.ndarray:
    """All records of a packed little-endian binary file, checking its size first.

    A size that is not a whole number of records is a truncated or foreign
    file: one :class:`LirisError` naming the file and the record size.
    """
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "scan file not found")
    size = path.stat().st_size
    if size % dtype.itemsize:
        raise LirisError(
            path,
            f"truncated or not a {what} file: size {size} bytes is not a multiple of the "
            f"{dtype.itemsize}-byte record ({describe_dtype(dtype)})",
        )
    return np.fromfile(path, dtype=dtype)


def record_dtype(fields: list[tuple[str, str]]) -> np.dtype:
    """A packed (unaligned) little-endian structured dtype."""
    return np.dtype(fields, align=False)


# --- rigid transforms -----------------------------------------------------------


def se3(rotation: np.ndarray, translation) -> np.ndarray:
    """``(N, 4, 4)`` (or ``(4, 4)``) transforms from rotations and translations."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    single = rotation.ndim == 2
    rotation = rotation.reshape(-1, 3, 3)
    out = np.tile(np.eye(4), (len(rotation), 1, 1))
    out[:, :3, :3] = rotation
    out[:, :3, 3] = translation.reshape(-1, 3)
    return out[0] if single else out


def rpy_zyx(roll, pitch, yaw) -> np.ndarray:
    """``Rz(yaw) · Ry(pitch) · Rx(roll)`` (radians), the x-y-z Euler convention of NCLT,
    the Oxford SDK and MulRan's calibration files; vectorised."""
    from scipy.spatial.transform import Rotation  # deferred: see the module's imports

    angles = np.column_stack([np.atleast_1d(roll), np.atleast_1d(pitch), np.atleast_1d(yaw)])
    return Rotation.from_euler("xyz", angles).as_matrix()


def quat_xyzw(q: np.ndarray, source: str | Path) -> np.ndarray:
    """``(N, 3, 3)`` rotations from ``(N, 4)`` quaternions in (x, y, z, w) order."""
    q = np.asarray(q, dtype=np.float64).reshape(-1, 4)
    norms = np.linalg.norm(q, axis=1)
    if np.any(norms < 1e-9) or not np.all(np.isfinite(q)):
        bad = int(np.argmax((norms < 1e-9) | ~np.isfinite(q).all(axis=1)))
        raise LirisError(source, f"zero or non-finite quaternion in pose row {bad + 1}")
    from scipy.spatial.transform import Rotation  # deferred: see the module's imports

    return Rotation.from_quat(q / norms[:, None]).as_matrix()


# --- text tables -----------------------------------------------------------------


def read_table(path: Path, columns: int, what: str, delimiter: str | None = None,
               skip_header: bool = False, nonfinite_ok: bool = False) -> np.ndarray:
    """A numeric table with ``columns`` values a row (comment lines ``#``/``%`` skipped).

    Rows with a wrong count, non-numbers or (unless ``nonfinite_ok``, for a
    dataset whose own files hold NaN rows, such as NCLT, filtered by
    :func:`finite_rows`) NaN/inf are one error naming ``path:line``.
    """
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, f"{what} file not found")
    rows = []
    lines = read_text(path, f"{what} file").splitlines()
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text[0] in "#%":
            continue
        if skip_header and not rows and not is_number(text.replace(",", " ").split()[0]):
            continue
        parts = text.split(delimiter) if delimiter else text.replace(",", " ").split()
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise LirisError(f"{path}:{number}", f"malformed {what} line (not numbers)") from None
        if len(values) != columns:
            raise LirisError(f"{path}:{number}",
                             f"malformed {what} line: {len(values)} values, expected {columns}")
        if not nonfinite_ok:
            check_finite(values, f"{path}:{number}", what)
        rows.append(values)
    if not rows:
        raise LirisError(path, f"{what} file has no pose rows")
    return np.asarray(rows, dtype=np.float64)


def read_stamp_column(path: Path, what: str) -> np.ndarray:
    """The first column of a text table as exact integers (ns/µs stamps lose digits as floats)."""
    stamps = []
    for number, line in enumerate(read_text(path, f"{what} file").splitlines(), start=1):
        text = line.strip()
        if not text or text[0] in "#%":
            continue
        head = text.replace(",", " ").split()[0]
        if not stamps and not is_number(head):
            continue  # header row
        try:
            if "e" in head.lower():  # scientific notation: exact only to float precision
                stamps.append(int(float(head)))
            else:
                stamps.append(int(head.split(".")[0]) if "." in head else int(head))
        except ValueError:
            raise LirisError(f"{path}:{number}", f"malformed {what} line (stamp)") from None
    return np.asarray(stamps, dtype=np.int64)


def finite_rows(table: np.ndarray, path: Path, what: str) -> np.ndarray:
    """Rows without NaN/inf; dropping some is a warning that counts them."""
    from lidar_iris_eval.errors import warn

    good = np.isfinite(table).all(axis=1)
    if not good.all():
        warn(path, f"skipped {int((~good).sum())} {what} rows with NaN or inf")
    if not good.any():
        raise LirisError(path, f"no finite {what} rows")
    return table[good]


# --- scans and time matching --------------------------------------------------------


def stem_stamps(paths: list[Path], source: Path) -> np.ndarray:
    """Integer stamps from numeric file stems (``1565012345123456789.bin``)."""
    try:
        return np.array([int(p.name.split(".")[0]) for p in paths], dtype=np.int64)
    except ValueError:
        bad = next(p for p in paths if not p.name.split(".")[0].isdigit())
        raise LirisError(bad, f"file name is not a numeric stamp (expected in {source})") from None


def list_files(folder: Path, suffix: str, what: str) -> list[Path]:
    """Files ending in ``suffix`` in ``folder`` (natural order of numeric stems)."""
    if not folder.is_dir():
        raise LirisError(folder, f"{what} folder not found")
    files = scan_entries(folder, lambda p: p.name.endswith(suffix))
    if not files:
        raise LirisError(folder, f"no {what} files (*{suffix})")
    return sorted(files, key=_natural_key)


def list_by_time(folder: Path, suffix: str, what: str,
                 stamps: Callable[[list[Path]], np.ndarray]) -> tuple[list[Path], np.ndarray]:
    """:func:`list_files` in time order: ``(files, seconds)``, sorted by ``stamps(files)``.

    For readers whose file names are the scans' times (Newer College,
    Wild-Places): the natural order of names need not be the time order, so
    the files are sorted by their stamps (stable: equal stamps keep name order).
    """
    files = list_files(folder, suffix, what)
    times = stamps(files)
    order = np.argsort(times, kind="stable")
    return pick(files, order), times[order]


def _natural_key(path: Path):
    import re

    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", path.name)]


def match_scans(scan_times: np.ndarray, pose_times: np.ndarray, poses: np.ndarray,
                tolerance: float, source: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """Scans kept, their poses (interpolated at the scan times), and how many were dropped.

    Times in seconds; a scan with no pose sample within ``tolerance`` has no
    pose and is dropped (warned with the count by
    :func:`~lidar_iris_eval.io.timematch.match_poses`).
    """
    keep, matched = match_poses(scan_times, pose_times, poses, tolerance, source)
    return keep, matched, int(len(scan_times) - len(keep))


def ns_to_seconds(stamps: np.ndarray, per_second: int) -> np.ndarray:
    """Integer stamps (``per_second`` ticks a second) to float seconds, exactly split."""
    stamps = np.asarray(stamps, dtype=np.int64)
    return (stamps // per_second).astype(np.float64) + (stamps % per_second) / per_second


def build(dataset: str, path: Path, name: str, scan_paths: list[Path], poses: np.ndarray,
          reader: Callable[..., Scan], sensor: str | None, pose_source: str,
          times: np.ndarray | None = None, unmatched: int = 0, records: list | None = None,
          frame_ids: np.ndarray | None = None, to_liris: np.ndarray | None = None,
          scan_note: str = "") -> DatasetSequence:
    """The :class:`DatasetSequence` every reader returns.

    ``poses`` are those of the dataset's sensor frame; with ``to_liris`` (the
    rotation taking that frame's coordinates to liris's z-up frame) they are
    turned into poses of the rotated frame, ``T · to_liris.T``, so the world
    points are unchanged.
    """
    if frame_ids is None:
        frame_ids = np.arange(len(scan_paths))
    poses = np.asarray(poses, float)
    if to_liris is not None:
        to_liris = np.asarray(to_liris, dtype=np.float64)
        poses = poses @ se3(to_liris.T, np.zeros(3))
        scan_note = f"to_liris={to_liris.round(12).tolist()}; {scan_note}"
    return DatasetSequence(
        name=name, path=path, scan_paths=list(scan_paths), poses=poses,
        times=None if times is None else np.asarray(times, dtype=np.float64),
        frame_ids=np.asarray(frame_ids), reader=reader, records=records, dataset=dataset,
        sensor_preset=sensor, pose_source=pose_source, unmatched=unmatched, to_liris=to_liris,
        scan_note=scan_note,
    )


def pick(values: list, keep: np.ndarray) -> list:
    """``values`` at the indices ``keep``."""
    return [values[i] for i in keep]


def require(path: Path, what: str, hint: str = "") -> Path:
    """``path`` if it is a file, else one error naming it."""
    if not path.is_file():
        raise LirisError(path, f"{what} not found{hint}")
    return path
