"""The GOSMatch authors' object layout, opened as a sequence whose scans are objects.

::

    00/bow.txt                 "n_vehicle,n_trunk,n_pole" per scan (0-based line i = scan i)
    00/centroids/000000.txt    one "x y z" line per object, LiDAR frame, sorted by class
    00/poses.txt, calib.txt    optional; or pass ``poses=`` / ``calib=``

This is the output of the authors' semantic front end (RangeNet++ labels, then
Euclidean clustering) released for KITTI 00. Opening it gives an
:class:`ObjectSequence`: the :class:`~lidar_iris_eval.io.sequence.Sequence`
machinery (poses, frame ids, fingerprint, length) with a reader whose "scan" is
an :class:`ObjectScan` (centroids and class codes) instead of points. Methods
that declare ``"objects"`` among their inputs (GOSMatch) read it; point
descriptors cannot, and say so.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.errors import options as option_names
from lidar_iris_eval.io.kitti import read_camera_poses_and_calib
from lidar_iris_eval.io.poses import camera_to_lidar
from lidar_iris_eval.io.sequence import Sequence, hash_file_samples

BOW_FILE = "bow.txt"
CENTROIDS_DIR = "centroids"
#: class code -> name, in the order of the bow.txt columns
OBJECT_CLASSES: tuple[str, ...] = ("vehicle", "trunk", "pole")


class ObjectScan(NamedTuple):
    """The objects of one scan: ``centroids (K, 3)`` float64 and ``classes (K,)`` int8.

    Centroids are in the LiDAR frame and sorted by class code (0 vehicle,
    1 trunk, 2 pole), the order GOSMatch's descriptors rely on.
    """

    centroids: np.ndarray
    classes: np.ndarray


def is_objects_layout(path: str | Path) -> bool:
    """True for a folder holding ``bow.txt`` and a ``centroids/`` folder."""
    path = Path(path)
    return (path / BOW_FILE).is_file() and (path / CENTROIDS_DIR).is_dir()


def read_bow(path: str | Path) -> np.ndarray:
    """``(N, 3)`` int64 object counts per scan from a ``bow.txt``."""
    path = Path(path)
    rows = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        parts = line.replace(",", " ").split()
        try:
            values = [int(float(p)) for p in parts]
        except ValueError:
            values = []
        if len(values) != len(OBJECT_CLASSES) or min(values) < 0:
            raise LirisError(
                path, f"line {number}: expected 3 non-negative counts "
                      f"(vehicle,trunk,pole), got {line.strip()!r}"
            )
        rows.append(values)
    if not rows:
        raise LirisError(path, "no object counts")
    return np.asarray(rows, dtype=np.int64)


def read_centroids(path: str | Path, counts: np.ndarray) -> ObjectScan:
    """Read one ``centroids/NNNNNN.txt`` whose class counts are ``counts``.

    The line count must equal ``counts.sum()``; the file names no classes, the
    counts say which lines are which.
    """
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "centroid file not found")
    text = path.read_text().split()
    try:
        values = np.array(text, dtype=np.float64)
    except ValueError:
        raise LirisError(path, "not a table of numbers (x y z per line expected)") from None
    if values.size % 3:
        raise LirisError(path, f"{values.size} numbers is not a multiple of 3 (x y z per line)")
    centroids = values.reshape(-1, 3)
    if len(centroids) != int(counts.sum()):
        raise LirisError(
            path, f"{len(centroids)} objects but {BOW_FILE} says {int(counts.sum())} "
                  f"({','.join(str(int(c)) for c in counts)})"
        )
    if not np.isfinite(centroids).all():
        raise LirisError(path, "NaN or inf coordinates")
    classes = np.repeat(np.arange(len(counts), dtype=np.int8), counts)
    return ObjectScan(centroids, classes)


@dataclass
class ObjectSequence(Sequence):
    """A sequence of object scans (the authors' layout) with LiDAR-frame poses.

    ``scan_paths`` are the centroid files; ``counts`` the ``bow.txt`` rows.
    ``scan(i)`` returns an :class:`ObjectScan`; there are no points.
    """

    counts: np.ndarray = field(default=None)  # type: ignore[assignment]
    bow_path: Path | None = None

    #: what a scan of this sequence provides (methods check their inputs against it)
    provides = frozenset({"objects"})
    has_labels = False
    has_objects = True

    def scan(self, index: int) -> ObjectScan:  # type: ignore[override]
        """The objects of scan ``index``."""
        return read_centroids(self.scan_paths[index], self.counts[index])

    def __getitem__(self, index: int) -> np.ndarray:  # type: ignore[override]
        raise LirisError(
            self.path, "an object sequence (bow.txt + centroids/) has no points; only methods "
                       "that read objects (gosmatch) can run on it"
        )

    def fingerprint(self) -> str:
        """Content fingerprint of ``bow.txt`` and the centroid files, for cache keys."""
        digest = hashlib.sha256()
        hash_file_samples(digest, ([self.bow_path] if self.bow_path else []) + self.scan_paths)
        return digest.hexdigest()[:16]


def open_objects(
    path: str | Path,
    poses: str | Path | None = None,
    calib: str | Path | None = None,
    **options,
) -> ObjectSequence:
    """Open the authors' object layout with KITTI camera-frame poses.

    Parameters
    ----------
    path : the folder with ``bow.txt`` and ``centroids/``.
    poses : KITTI pose file (camera frame), default ``poses.txt`` in ``path``.
    calib : KITTI ``calib.txt`` with ``Tr``, default ``calib.txt`` in ``path``;
        needed to express the poses in the LiDAR frame the centroids are in.
    options : none apply (scan-folder options are refused, naming them).
    """
    root = Path(path)
    if options:
        raise LirisError(root, f"{option_names(options)}: not applicable to an object "
                               f"layout (bow.txt + centroids/); it takes poses and calib only")
    if not is_objects_layout(root):
        raise LirisError(root, f"not an object layout: expected {BOW_FILE} and {CENTROIDS_DIR}/")
    bow_path = root / BOW_FILE
    counts = read_bow(bow_path)
    folder = root / CENTROIDS_DIR
    scan_paths = sorted(
        (p for p in folder.iterdir() if p.suffix == ".txt" and p.stem.isdigit()),
        key=lambda p: int(p.stem),
    )
    if not scan_paths:
        raise LirisError(folder, "no centroid files (NNNNNN.txt)")
    if len(scan_paths) != len(counts):
        raise LirisError(
            bow_path, f"{len(counts)} count rows but {len(scan_paths)} files in {folder}"
        )
    pose_path = Path(poses) if poses is not None else root / "poses.txt"
    if not pose_path.is_file():
        raise LirisError(pose_path, "pose file not found (KITTI camera-frame poses needed)")
    calib_path = Path(calib) if calib is not None else root / "calib.txt"
    camera_poses, tr = read_camera_poses_and_calib(pose_path, calib_path, scan_paths, folder)
    return ObjectSequence(
        name=root.name,
        path=root,
        scan_paths=scan_paths,
        poses=camera_to_lidar(camera_poses, tr),
        camera_poses=camera_poses,
        calib=tr,
        counts=counts,
        bow_path=bow_path,
    )
