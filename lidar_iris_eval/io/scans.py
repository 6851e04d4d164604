"""Reading single scans from disk, with the input checks every reader shares.

A scan is an ``(N, 3)`` float32 array of points in the sensor frame, plus an
optional ``(N,)`` intensity. Non-finite points are dropped with a warning that
counts them; an empty scan is an error, because every descriptor would return
garbage for it and the user should know which file is at fault.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from lidar_iris_eval.errors import LirisError, warn

KITTI_POINT_BYTES = 16  # float32 x, y, z, intensity


class Scan(NamedTuple):
    """Points ``(N, 3)`` float32 and intensity ``(N,)`` float32 or None."""

    points: np.ndarray
    intensity: np.ndarray | None


def clean_points(points: np.ndarray, intensity: np.ndarray | None, source: str | Path) -> Scan:
    """Drop non-finite points (warning with their count); reject empty scans.

    ``points`` may have more than 3 columns; only the first three are kept.
    """
    points = np.asarray(points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] < 3:
        raise LirisError(source, f"expected an (N, 3) point array, got shape {points.shape}")
    xyz = points[:, :3]
    finite = np.isfinite(xyz).all(axis=1)
    n_bad = int(len(finite) - np.count_nonzero(finite))
    if n_bad:
        warn(source, f"dropped {n_bad} of {len(finite)} points with NaN or inf coordinates")
        xyz = xyz[finite]
        if intensity is not None:
            intensity = intensity[finite]
    if len(xyz) == 0:
        raise LirisError(source, "empty scan (no valid points)")
    if intensity is not None:
        intensity = np.ascontiguousarray(intensity, dtype=np.float32)
    return Scan(np.ascontiguousarray(xyz), intensity)


def read_kitti_bin(path: str | Path) -> Scan:
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
    return clean_points(data[:, :3], data[:, 3], path)


def read_npy(path: str | Path) -> Scan:
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
    return clean_points(data[:, :3], intensity, path)
