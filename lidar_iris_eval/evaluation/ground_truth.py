"""Ground truth from poses alone: positive pairs and revisit queries.

Conventions (see PROTOCOLS.md, each is named in every output):

* **radius** – a pair is positive when the distance between the two frames'
  translations is strictly below it (default 4 m).
* **distance** – ``3d`` Euclidean, or ``planar`` in the ground plane: x–z for
  camera-frame poses (KITTI cameras have y down), x–y for LiDAR-frame poses.
* **frame** – ``camera`` uses the KITTI camera poses as given (what the
  paper's counts use), ``lidar`` the LiDAR-frame poses ``inv(Tr)·T·Tr``.
  They differ by up to ~0.6 m under rotation, which flips pairs near 4 m.
* **exclude** (E) – query i may only match database frames j ≤ i − E; it is
  a *revisit query* when at least one of those lies within the radius.

Pairs are counted as ordered pairs (i, j), i ≠ j, as the paper does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lidar_iris_eval.errors import LirisError, option

PLANAR_AXES = {"camera": (0, 2), "lidar": (0, 1)}
DISTANCES = ("3d", "planar")
FRAMES = ("camera", "lidar")


def gt_coordinates(
    positions: np.ndarray, frame: str = "camera", distance: str = "3d"
) -> np.ndarray:
    """The coordinates whose Euclidean distance defines ground truth.

    ``positions`` are ``(N, 3)`` translations in ``frame``; planar distance keeps
    the two ground-plane axes of that frame.
    """
    if frame not in FRAMES:
        raise LirisError(option("pose_frame", frame), "unknown pose frame; choose camera or lidar")
    if distance not in DISTANCES:
        raise LirisError(option("distance", distance), "unknown distance; choose 3d or planar")
    positions = np.asarray(positions, dtype=np.float64)
    if distance == "planar":
        return positions[:, list(PLANAR_AXES[frame])]
    return positions


def ground_plane_axes(frame: str) -> tuple[int, int]:
    """Indices of the two ground-plane axes for trajectory plots."""
    return PLANAR_AXES[frame]


def positive_pairs(coords: np.ndarray, radius: float = 4.0) -> np.ndarray:
    """Unordered pairs ``(i, j)``, ``i < j``, closer than ``radius`` (strictly).

    Uses a k-d tree, so memory grows with the number of positives, not N².
    """
    if len(coords) < 2:
        return np.empty((0, 2), dtype=np.int64)
    tree = cKDTree(coords)
    pairs = tree.query_pairs(radius, output_type="ndarray").astype(np.int64)
    if len(pairs) == 0:
        return np.empty((0, 2), dtype=np.int64)
    pairs.sort(axis=1)
    dist = np.linalg.norm(coords[pairs[:, 0]] - coords[pairs[:, 1]], axis=1)
    pairs = pairs[dist < radius]
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    return pairs[order]


@dataclass(frozen=True)
class GroundTruth:
    """Positive pairs and revisit queries of one sequence under one convention."""

    n_frames: int
    radius: float
    exclude: int
    distance: str
    frame: str
    pairs: np.ndarray  # (K, 2) unordered positive pairs, i < j
    revisit: np.ndarray  # (N,) bool: query has a positive j <= i - exclude

    @property
    def n_positive_pairs(self) -> int:
        """Positive ordered pairs (each unordered pair counts twice)."""
        return 2 * len(self.pairs)

    @property
    def n_negative_pairs(self) -> int:
        """Negative ordered pairs, i ≠ j."""
        return self.n_frames * (self.n_frames - 1) - self.n_positive_pairs

    @property
    def n_revisits(self) -> int:
        return int(np.count_nonzero(self.revisit))

    def positive_matrix(self) -> np.ndarray:
        """Dense ``(N, N)`` bool matrix of positives (diagonal False)."""
        matrix = np.zeros((self.n_frames, self.n_frames), dtype=bool)
        matrix[self.pairs[:, 0], self.pairs[:, 1]] = True
        matrix[self.pairs[:, 1], self.pairs[:, 0]] = True
        return matrix

    def summary(self) -> dict:
        """Counts and conventions as a JSON-ready dict."""
        return {
            "frames": self.n_frames,
            "radius_m": self.radius,
            "exclude": self.exclude,
            "distance": self.distance,
            "pose_frame": self.frame,
            "positive_ordered_pairs": self.n_positive_pairs,
            "negative_ordered_pairs": self.n_negative_pairs,
            "revisit_queries": self.n_revisits,
        }


def revisit_queries(pairs: np.ndarray, n_frames: int, exclude: int) -> np.ndarray:
    """Queries ``i`` with a positive partner ``j <= i - exclude``."""
    revisit = np.zeros(n_frames, dtype=bool)
    if len(pairs):
        later, earlier = pairs[:, 1], pairs[:, 0]
        revisit[later[later - earlier >= exclude]] = True
    return revisit


def compute_ground_truth(
    positions: np.ndarray,
    radius: float = 4.0,
    exclude: int = 30,
    distance: str = "3d",
    frame: str = "camera",
) -> GroundTruth:
    """Ground truth from ``(N, 3)`` translations expressed in ``frame``."""
    if not 0 < radius < np.inf:  # NaN fails too
        raise LirisError(option("radius", radius), "radius must be a positive finite number")
    if exclude < 1:
        raise LirisError(option("exclude", exclude), "exclusion window must be at least 1 frame")
    coords = gt_coordinates(positions, frame, distance)
    pairs = positive_pairs(coords, radius)
    return GroundTruth(
        n_frames=len(coords),
        radius=float(radius),
        exclude=int(exclude),
        distance=distance,
        frame=frame,
        pairs=pairs,
        revisit=revisit_queries(pairs, len(coords), exclude),
    )


def pair_distances(positions: np.ndarray, i: np.ndarray, j: np.ndarray, frame: str,
                   distance: str) -> np.ndarray:
    """Ground-truth distances (metres) between frames ``i[k]`` and ``j[k]``."""
    coords = gt_coordinates(positions, frame, distance)
    return np.linalg.norm(coords[np.asarray(i)] - coords[np.asarray(j)], axis=1)
