"""Reading single scans from disk, with the input checks every reader shares.

A scan is an ``(N, 3)`` float32 array of points in the sensor frame, plus an
optional ``(N,)`` intensity and optional ``(N,)`` per-point labels (SemanticKITTI
``.label`` files: uint32, semantic class in the low 16 bits, instance id in the
high 16). Non-finite points are dropped, with their labels, and a warning that
counts them; an empty scan is an error, because every descriptor would return
garbage for it and the user should know which file is at fault.

Plausibility rules (each has a name, and its error says it in one line):

* ``finite-plausible-coordinates``: after non-finite points are dropped, at
  most :data:`IMPLAUSIBLE_FRACTION` of the points may have a coordinate
  farther than :data:`MAX_COORDINATE_M` from the sensor or a non-zero
  magnitude below :data:`MIN_NONZERO_COORDINATE_M` (subnormal). Random bytes, a float64
  file read as float32 and a wrongly decoded PCD body all break this rule
  (their exponents are spread over the whole float32 range); a real scan,
  even in a global UTM frame, does not.
* ``label-count``: one label per stored point.
* ``label-classes``: every semantic class (``label & 0xFFFF``) is a
  SemanticKITTI class id (:data:`SEMANTIC_KITTI_CLASSES`).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from lidar_iris_eval.errors import LirisError, warn

KITTI_POINT_BYTES = 16  # float32 x, y, z, intensity
LABEL_BYTES = 4  # SemanticKITTI: one little-endian uint32 per point
LABEL_SUFFIX = ".label"

#: rule ``finite-plausible-coordinates``: no LiDAR sees 1000 km; a sensor-frame (or even
#: UTM-frame) coordinate beyond this is a decoding error, not a measurement
MAX_COORDINATE_M = 1.0e6
#: same rule: a subnormal float32 (non-zero, below 1.2e-38) is a decoding error: sensor
#: arithmetic gives exact zeros or normal numbers (r cos 90 deg is 1e-15, not subnormal)
MIN_NONZERO_COORDINATE_M = float(np.finfo(np.float32).tiny)
#: same rule: the share of points allowed to break it (a few stray returns are tolerated)
IMPLAUSIBLE_FRACTION = 0.01

#: rule ``label-classes``: the class ids of the SemanticKITTI label definition
#: (semantic-kitti.yaml of the semantic-kitti-api): static 0-99 and moving 252-259
SEMANTIC_KITTI_CLASSES = frozenset({
    0, 1, 10, 11, 13, 15, 16, 18, 20, 30, 31, 32, 40, 44, 48, 49, 50, 51, 52, 60, 70, 71,
    72, 80, 81, 99, 252, 253, 254, 255, 256, 257, 258, 259,
})
_KNOWN_CLASS = np.zeros(1 << 16, dtype=bool)
_KNOWN_CLASS[sorted(SEMANTIC_KITTI_CLASSES)] = True


class Scan(NamedTuple):
    """One scan as read from disk.

    Attributes
    ----------
    points : ``(N, 3)`` float32, sensor (LiDAR) frame.
    intensity : ``(N,)`` float32, or None when the format has none.
    labels : ``(N,)`` uint32 raw SemanticKITTI labels, or None; the semantic
        class is ``labels & 0xFFFF``, the instance ``labels >> 16``.
    """

    points: np.ndarray
    intensity: np.ndarray | None
    labels: np.ndarray | None = None


def clean_points(
    points: np.ndarray,
    intensity: np.ndarray | None,
    source: str | Path,
    labels: np.ndarray | None = None,
    labels_source: str | Path | None = None,
) -> Scan:
    """Drop non-finite points (warning with their count); reject empty scans.

    ``points`` may have more than 3 columns; only the first three are kept.
    ``labels`` (one per point *as stored*, before dropping) are filtered with
    the points; a count that differs from the stored points is an error
    naming ``labels_source``.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] < 3:
        raise LirisError(source, f"expected an (N, 3) point array, got shape {points.shape}")
    if labels is not None and len(labels) != len(points):
        raise LirisError(
            labels_source or source,
            f"{len(labels)} labels but {len(points)} points in {source}; counts must be equal",
        )
    xyz = np.ascontiguousarray(points[:, :3])
    # one pass over the contiguous copy (fast); the per-point mask (3x slower on a
    # full-resolution scan, once per descriptor) only when something is not finite
    if not np.isfinite(xyz).all():
        finite = np.isfinite(xyz).all(axis=1)
        n_bad = int(len(finite) - np.count_nonzero(finite))
        warn(source, f"dropped {n_bad} of {len(finite)} points with NaN or inf coordinates")
        xyz = xyz[finite]
        if intensity is not None:
            intensity = intensity[finite]
        if labels is not None:
            labels = labels[finite]
    if len(xyz) == 0:
        raise LirisError(source, "empty scan (no valid points)")
    check_plausible(xyz, source)
    if intensity is not None:
        intensity = np.ascontiguousarray(intensity, dtype=np.float32)
    if labels is not None:
        labels = np.ascontiguousarray(labels, dtype=np.uint32)
    return Scan(xyz, intensity, labels)


def check_plausible(xyz: np.ndarray, source: str | Path) -> None:
    """Rule ``finite-plausible-coordinates`` (module docstring) on finite ``(N, 3)`` points."""
    magnitude = np.abs(xyz)
    # fast path (a real scan): nothing far, nothing tiny but exact zeros
    if (magnitude.max() <= MAX_COORDINATE_M
            and np.count_nonzero(magnitude < MIN_NONZERO_COORDINATE_M)
            == np.count_nonzero(magnitude == 0)):
        return
    bad = ((magnitude > MAX_COORDINATE_M)
           | ((magnitude < MIN_NONZERO_COORDINATE_M) & (magnitude > 0))).any(axis=1)
    n_bad = int(np.count_nonzero(bad))
    if n_bad > IMPLAUSIBLE_FRACTION * len(xyz):
        raise LirisError(
            source,
            f"implausible coordinates in {n_bad} of {len(xyz)} points (beyond "
            f"{MAX_COORDINATE_M:.0e} m or subnormal; "
            f"rule finite-plausible-coordinates): not float32 x, y, z data (random bytes, "
            f"a float64 file?)",
        )


def check_label_classes(labels: np.ndarray, source: str | Path) -> None:
    """Rule ``label-classes``: every semantic class is a SemanticKITTI class id."""
    unknown = ~_KNOWN_CLASS[labels & 0xFFFF]
    if unknown.any():
        first = int(np.argmax(unknown))
        raise LirisError(
            source,
            f"{int(np.count_nonzero(unknown))} of {len(labels)} labels have a class id that "
            f"is not a SemanticKITTI class (first: {int(labels[first] & 0xFFFF)} at point "
            f"{first}; rule label-classes)",
        )


def read_labels(path: str | Path) -> np.ndarray:
    """Read a SemanticKITTI ``.label`` file: ``(N,)`` uint32, little-endian.

    The class ids are checked (rule ``label-classes``); the count is checked
    against the scan by the caller (rule ``label-count``).
    """
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "label file not found")
    size = path.stat().st_size
    if size % LABEL_BYTES:
        raise LirisError(
            path, f"truncated label file: size {size} bytes is not a multiple of {LABEL_BYTES}"
        )
    labels = np.fromfile(path, dtype="<u4").astype(np.uint32, copy=False)
    check_label_classes(labels, path)
    return labels


def with_labels(read: Callable[[Path], Scan], path: Path, labels_path: Path) -> Scan:
    """Read scan ``path`` with ``read`` and attach the labels of ``labels_path``.

    Readers that accept ``labels=``/``labels_source=`` filter them together
    with dropped points; for any other reader the label count must equal the
    number of points it returns.
    """
    labels = read_labels(labels_path)
    try:
        params = inspect.signature(read).parameters
    except (TypeError, ValueError):
        params = {}
    if "labels" in params:
        return read(path, labels=labels, labels_source=labels_path)
    scan = read(path)
    if len(labels) != len(scan.points):
        raise LirisError(
            labels_path,
            f"{len(labels)} labels but {len(scan.points)} points in {path}; counts must be equal",
        )
    return scan._replace(labels=labels)


def read_kitti_bin(
    path: str | Path, labels: np.ndarray | None = None, labels_source: Path | None = None
) -> Scan:
    """Read a KITTI ``.bin`` scan: float32 x, y, z, intensity, 16 bytes a point."""
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "scan file not found")
    size = path.stat().st_size
    if size % KITTI_POINT_BYTES:
        raise LirisError(
            path,
            f"truncated or not a KITTI scan: size {size} bytes is not a multiple of "
            f"{KITTI_POINT_BYTES} (float32 x, y, z, intensity)",
        )
    data = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    return clean_points(data[:, :3], data[:, 3], path, labels, labels_source)


def read_npy(
    path: str | Path, labels: np.ndarray | None = None, labels_source: Path | None = None
) -> Scan:
    """Read a ``.npy`` scan of shape (N, 3) or (N, 4+) (the 4th column is intensity)."""
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "scan file not found")
    try:
        data = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as err:
        raise LirisError(path, f"not a readable .npy array ({err})") from None
    if data.ndim != 2 or data.shape[1] < 3:
        raise LirisError(path, f"expected an (N, 3) or (N, 4) array, got shape {data.shape}")
    intensity = data[:, 3] if data.shape[1] > 3 else None
    return clean_points(data[:, :3], intensity, path, labels, labels_source)
