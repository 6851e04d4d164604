"""Where the poses that place scans in a local map come from.

* ``gt``: the sequence's own LiDAR-frame poses (an oracle odometry: no drift);
* ``kiss-icp``: poses estimated from the scans alone by KISS-ICP (Vizzo et al.,
  RA-L 2023; ``pip install "lidar-iris-eval[odometry]"``), as MapClosures does.
  KISS-ICP's first pose is the identity; its poses are in the frame of the
  first scan.
"""

from __future__ import annotations

import sys

import numpy as np
from tqdm import tqdm

from lidar_iris_eval.errors import LirisError

#: the pose sources (module docstring)
ODOMETRY_SOURCES = ("gt", "kiss-icp")


def odometry_poses(seq, source: str = "gt", progress: bool = False) -> np.ndarray:
    """``(N, 4, 4)`` world-from-LiDAR poses of every scan of ``seq`` from ``source``."""
    if source == "gt":
        return np.asarray(seq.poses, dtype=np.float64)
    if source == "kiss-icp":
        return _kiss_icp(seq, progress)
    raise LirisError("odometry", f"unknown odometry {source!r}; choose from "
                                 f"{', '.join(ODOMETRY_SOURCES)}")


def _kiss_icp(seq, progress: bool) -> np.ndarray:  # pragma: no cover - optional extra
    try:
        from kiss_icp.config import KISSConfig
        from kiss_icp.kiss_icp import KissICP
    except ImportError:
        raise LirisError("odometry kiss-icp", 'needs the optional extra: pip install '
                                              '"lidar-iris-eval[odometry]"') from None
    config = KISSConfig()
    config.data.max_range = 100.0
    config.data.deskew = False
    odom = KissICP(config=config)
    poses = np.empty((len(seq), 4, 4))
    for i in tqdm(range(len(seq)), desc="kiss-icp", unit="scan", file=sys.stderr,
                  disable=not progress, leave=False):
        pts = np.asarray(seq[i], dtype=np.float64)[:, :3]
        odom.register_frame(pts, np.zeros(len(pts)))
        poses[i] = odom.last_pose
    return poses
