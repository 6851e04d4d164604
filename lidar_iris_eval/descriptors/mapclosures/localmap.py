"""Local maps at every frame, the smallest builder this method needs.

Until the shared local-map package (issue 28) lands, this module builds the
input MapClosures reads, under the rule shared with ESM:

* the local map of frame ``i`` holds the scans of frames ``i - window < j <= i``
  (``window`` = protocol 1's exclusion window E), so a query's map never
  holds a scan of a database frame ``j <= i - E``;
* each scan is placed with the sequence's LiDAR-frame poses (``gt``: an
  oracle odometry) in the LiDAR frame of frame ``i``, and only points within
  a ``radius`` cylinder (xy distance) of frame ``i``'s origin are kept;
* the points go into MapClosures' own voxel map (``map_closures.VoxelMap``:
  ``voxel`` m voxels of at most 20 points, each at least ``voxel/sqrt(20)``
  from the others), as its pipeline does, and the map's points are the input
  of the density image.

Each scan is first thinned by the same voxel map on its own (per-scan
feature, cached by the extraction), so the local map is the voxel map of the
thinned scans; the voxel map drops a point too close to one already kept, so
thinning first keeps at most what integrating the raw scan would keep.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.mapclosures import backend


@dataclass(frozen=True)
class LocalMapSettings:
    """How the per-frame local maps are built (recorded in metrics.json via the params)."""

    window: int = 30
    radius: float = 50.0
    voxel: float = 0.5
    odometry: str = "gt"

    def as_dict(self) -> dict:
        """The settings as plain values."""
        return {"window": self.window, "radius": self.radius, "voxel": self.voxel,
                "odometry": self.odometry}


def _voxel_map(voxel: float, max_distance: float = 1e9):
    return backend.pybind()._VoxelMap(float(voxel), float(max_distance))


def thin_scan(points: np.ndarray, voxel: float) -> np.ndarray:
    """``(K, 3)`` float32: the points MapClosures' voxel map keeps of one scan."""
    pb = backend.pybind()
    vmap = _voxel_map(voxel)
    vmap._add_points(pb._Vector3dVector(np.asarray(points, dtype=np.float64)))
    return np.asarray(vmap._point_cloud(), dtype=np.float32).reshape(-1, 3)


def frame_local_map(scans, poses: np.ndarray, i: int, settings: LocalMapSettings) -> np.ndarray:
    """``(M, 3)`` float64 local map of frame ``i`` in frame ``i``'s LiDAR frame.

    ``scans[j]`` are frame ``j``'s (thinned) points in its LiDAR frame and
    ``poses`` the ``(N, 4, 4)`` LiDAR-frame poses; frames
    ``max(0, i - window + 1) .. i`` are used.
    """
    pb = backend.pybind()
    inv_i = np.linalg.inv(poses[i])
    vmap = _voxel_map(settings.voxel)
    r2 = settings.radius ** 2
    for j in range(max(0, i - settings.window + 1), i + 1):
        T = inv_i @ poses[j]
        pts = np.asarray(scans[j], dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        pts = pts[np.einsum("ij,ij->i", pts[:, :2], pts[:, :2]) <= r2]
        if len(pts):
            vmap._add_points(pb._Vector3dVector(pts))
    return np.asarray(vmap._point_cloud(), dtype=np.float64).reshape(-1, 3)
