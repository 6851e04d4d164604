"""A sequence given by its poses alone (``liris eval --poses POSES [--times T] --loops F``).

Scoring another system's loops needs the poses and times, not the scans: a
:class:`PoseSequence` has everything :func:`~lidar_iris_eval.evaluation.external_loops.
evaluate_loops` and the run writer read (``poses``, ``times``, ``frame_ids``,
``positions``, ``fingerprint``) and no scans. Its poses are used as given, as
``liris gt --poses`` does: with ``calib`` (a KITTI ``calib.txt``) KITTI camera
poses are turned into LiDAR poses, otherwise the given poses serve both frames.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.io.poses import camera_to_lidar, read_calib, read_pose_file


@dataclass
class PoseSequence:
    """Poses (and times) without scans."""

    name: str
    path: Path
    poses: np.ndarray
    camera_poses: np.ndarray | None = None
    times: np.ndarray | None = None
    frame_ids: np.ndarray = field(default=None)  # type: ignore[assignment]
    scan_paths: tuple = ()

    def __post_init__(self) -> None:
        if self.frame_ids is None:
            self.frame_ids = np.arange(len(self.poses))

    def __len__(self) -> int:
        return len(self.poses)

    def positions(self, frame: str = "lidar") -> np.ndarray:
        if frame == "camera" and self.camera_poses is not None:
            return self.camera_poses[:, :3, 3].copy()
        return self.poses[:, :3, 3].copy()

    def resolve_pose_frame(self, frame: str) -> str:
        return frame

    def fingerprint(self) -> str:
        digest = hashlib.sha256(np.ascontiguousarray(self.poses).tobytes())
        if self.times is not None:
            digest.update(np.ascontiguousarray(self.times).tobytes())
        return digest.hexdigest()[:16]


def open_pose_sequence(poses: str | Path, times: str | Path | None = None,
                       calib: str | Path | None = None, pose_format: str = "auto"
                       ) -> PoseSequence:
    """Read a KITTI or TUM pose file (TUM stamps are the times unless ``times`` is given)."""
    path = Path(poses)
    stamps, given = read_pose_file(path, pose_format)
    if times is not None:
        from lidar_iris_eval.io.loops import read_keyframes

        stamps = read_keyframes(times=times).times  # one number per line, lines named
        if len(stamps) != len(given):
            raise LirisError(times, f"{len(stamps)} times for {len(given)} poses in {path}")
    camera = None
    lidar = given
    if calib is not None:
        camera, lidar = given, camera_to_lidar(given, read_calib(calib))
    else:
        camera = given
    return PoseSequence(path.stem, path, lidar, camera,
                        None if stamps is None else np.asarray(stamps, dtype=np.float64))
