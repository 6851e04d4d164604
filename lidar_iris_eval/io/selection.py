"""Frame selection that works the same on every sequence format.

``--frames START:STOP[:STEP]``, ``--every N`` and ``--min-distance D`` are
applied by :func:`select_frames` after a reader opened the sequence, so a
KITTI layout, a scan folder and a ROS bag select frames identically:

1. ``frames`` keeps the Python slice ``START:STOP:STEP`` of the frame indices
   (0-based, STOP excluded, negative values count from the end);
2. ``min_distance`` then keeps the first of those and each later one at least
   ``D`` metres (3-D, LiDAR poses) from the last kept one;
3. ``every`` then keeps every N-th of the remaining frames.

The selected sequence keeps the original frame ids (``frame_ids``), so
matches and figures still name the files' frame numbers; its fingerprint
covers only the kept scans, so cached descriptors of another selection are
never reused by mistake.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.sequence import Sequence
from lidar_iris_eval.io.timematch import select_keyframes

#: reader keywords handled here rather than by the readers
SELECTION_KEYS = ("frames", "every", "min_distance")
#: per-scan fields that are never subset (whole-sequence constants)
_CONSTANT_FIELDS = {"calib", "name", "path", "labels_dir", "topic"}


def parse_frames(text: str | slice | None) -> slice | None:
    """``"START:STOP[:STEP]"`` (any part may be empty) to a slice."""
    if text is None or isinstance(text, slice):
        return text
    parts = str(text).split(":")
    if len(parts) not in (2, 3):
        hint = (f" ({text.strip()} alone is a count only for liris simulate and bench; here "
                f"0:{text.strip()} keeps the first {text.strip()} frames)"
                if str(text).strip().isdigit() else "")
        raise LirisError(f"--frames {text}", "a frame range here: expected START:STOP or "
                                             f"START:STOP:STEP, e.g. 0:200:2{hint}")
    try:
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise LirisError(f"--frames {text}", "START, STOP and STEP must be integers") from None
    if len(values) == 3 and values[2] is not None and values[2] < 1:
        raise LirisError(f"--frames {text}", "STEP must be at least 1")
    return slice(*values)


def selected_indices(n_frames: int, positions: np.ndarray, frames=None, every: int = 1,
                     min_distance: float = 0.0) -> np.ndarray:
    """Indices (into the opened sequence) kept by the selection, in order."""
    window = parse_frames(frames)
    index = np.arange(n_frames)
    if window is not None:
        index = index[window]
    if len(index) == 0:
        raise LirisError(f"--frames {frames}", f"selects no frame of the {n_frames}")
    chosen = select_keyframes(np.asarray(positions)[index], every, min_distance)
    return index[chosen]


def subset_sequence(seq: Sequence, keep: np.ndarray) -> Sequence:
    """A copy of ``seq`` with only the scans ``keep`` (indices, in order).

    Every per-scan field (a list or array with one entry per scan) is subset;
    whole-sequence fields (calibration, name, folders) are kept.
    """
    keep = np.asarray(keep, dtype=np.int64)
    n = len(seq)
    changes = {}
    for f in dataclasses.fields(seq):
        if not f.init or f.name in _CONSTANT_FIELDS:
            continue
        value = getattr(seq, f.name)
        if isinstance(value, list) and len(value) == n:
            changes[f.name] = [value[i] for i in keep]
        elif isinstance(value, np.ndarray) and value.ndim >= 1 and value.shape[0] == n:
            changes[f.name] = value[keep]
    return dataclasses.replace(seq, **changes)


def select_frames(seq: Sequence, frames=None, every: int | None = None,
                  min_distance: float | None = None) -> Sequence:
    """The sequence restricted to the selected frames (see the module docstring)."""
    every = 1 if every is None else every
    min_distance = 0.0 if min_distance is None else min_distance
    if frames is None and every == 1 and min_distance == 0.0:
        return seq
    keep = selected_indices(len(seq), seq.poses[:, :3, 3], frames, every, min_distance)
    return subset_sequence(seq, keep)


def open_kitti_with_options(path: Path, poses=None, calib=None, **options) -> Sequence:
    """A KITTI layout opened with reader options (``pose_format``, ``lidar_frame``,
    ``times``, ``tolerance``) or a TUM pose file.

    The scans are read as a folder of scans (``velodyne/``), with the
    layout's pose file, ``calib.txt`` and ``times.txt`` found beside them, so
    a TUM file is matched to the scan times exactly as for a scan folder.
    """
    from lidar_iris_eval.io.folder import open_folder
    from lidar_iris_eval.io.kitti import find_kitti_poses

    seq_dir = path.parent if path.name == "velodyne" else path
    if poses is None:
        poses = find_kitti_poses(seq_dir)
        if poses is None:
            raise LirisError(seq_dir, f"no poses: expected {seq_dir / 'poses.txt'} or "
                                      f"../../poses/{seq_dir.name}.txt")
    if calib is None and (seq_dir / "calib.txt").is_file():
        calib = seq_dir / "calib.txt"
    seq = open_folder(seq_dir / "velodyne", poses=poses, calib=calib, **options)
    return dataclasses.replace(seq, name=seq_dir.name, path=seq_dir)


def needs_folder_reader(poses, options: dict) -> bool:
    """True when a KITTI layout must be read through the folder reader."""
    if options:
        return True
    if poses is None:
        return False
    from lidar_iris_eval.io.poses import read_pose_file

    return read_pose_file(Path(poses))[0] is not None  # timestamped: a TUM file
