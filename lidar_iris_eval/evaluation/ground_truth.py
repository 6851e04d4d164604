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
from lidar_iris_eval.matching.blocks import frame_limits

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


def within_radius(dist: np.ndarray | float, radius: float, inclusive: bool = False):
    """True where ``dist`` counts as within ``radius``: strict ``<``, or ``<=`` if ``inclusive``.

    The one radius test of ground truth: :func:`positive_pairs`,
    :func:`revisit_queries_within` and ``liris gt --explain`` all use it.
    """
    dist = np.asarray(dist, dtype=np.float64)
    return dist <= radius if inclusive else dist < radius


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
    pairs = pairs[within_radius(dist, radius)]
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
    revisit: np.ndarray  # (N,) bool: query has a positive j <= i - exclude (or <= limits[i])
    #: (N,) last database frame of each query, -1 when it is not a query; None = i - exclude
    limits: np.ndarray | None = None

    def query_limits(self) -> np.ndarray:
        """``(N,)`` last database frame each query may match (``-1``: not a query)."""
        if self.limits is not None:
            return self.limits
        return frame_limits(self.n_frames, self.exclude)

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


def database_limits(n_frames: int, conv, times: np.ndarray | None = None,
                    source: str = "scan times") -> np.ndarray:
    """``(N,)`` last database index each query may match, ``-1`` when it is not a query.

    ``conv`` is a :class:`~lidar_iris_eval.evaluation.settings.Settings`. Frame
    windows give ``i - E``. Time windows need ``times`` (seconds, one per scan,
    non-decreasing) and follow ``conv.window_rule``.
    """
    index = np.arange(n_frames)
    if getattr(conv, "database_frames", None) is not None:
        # a fixed database, the first part of the sequence (BEVPlace's split)
        limits = np.where(index >= conv.query_start, conv.database_frames - 1, -1)
    elif conv.exclude_seconds is None:
        if conv.exclude is None or conv.exclude < 1:
            raise LirisError(f"convention {conv.name}", "exclusion window must be at least 1")
        limits = index - int(conv.exclude)
    else:
        if times is None:
            raise LirisError(
                f"--exclude {conv.exclude_seconds:g}s",
                "a window in seconds needs scan times (times.txt beside the scans, --times, "
                "or bag timestamps)")
        times = np.asarray(times, dtype=np.float64)
        if len(times) != n_frames:
            raise LirisError(source, f"{len(times)} times for {n_frames} scans")
        if not np.all(np.isfinite(times)) or np.any(np.diff(times) < 0):
            raise LirisError(source, "scan times must be finite and non-decreasing")
        seconds = float(conv.exclude_seconds)
        # last j with t_j <= t_i - T
        limits = np.searchsorted(times, times - seconds, side="right") - 1
        if conv.window_rule == "logg3d":
            limits = np.where(times - times[0] >= seconds, limits + 1, -1)
            limits = np.minimum(limits, index - 1)
    limits = np.where(limits >= 0, limits, -1)
    if not conv.last_frame_query and n_frames:
        limits[-1] = -1
    return limits.astype(np.int64)


def revisit_queries_within(coords: np.ndarray, limits: np.ndarray, radius: float,
                           inclusive: bool = False) -> np.ndarray:
    """``(N,)`` bool: query ``i`` has a database frame ``j <= limits[i]`` within ``radius``.

    ``coords`` are the ground-truth coordinates (:func:`gt_coordinates`).
    """
    coords = np.asarray(coords, dtype=np.float64)
    n = len(coords)
    revisit = np.zeros(n, dtype=bool)
    if n < 2:
        return revisit
    # query_pairs is inclusive (<= r); trim to strict unless asked
    pairs = cKDTree(coords).query_pairs(radius, output_type="ndarray").astype(np.int64)
    if len(pairs) == 0:
        return revisit
    pairs.sort(axis=1)
    if not inclusive:
        dist = np.linalg.norm(coords[pairs[:, 0]] - coords[pairs[:, 1]], axis=1)
        pairs = pairs[within_radius(dist, radius)]
    early, late = pairs[:, 0], pairs[:, 1]
    ok = early <= limits[late]
    revisit[late[ok]] = True
    return revisit


def ground_truth_for(positions: np.ndarray, settings, times: np.ndarray | None = None,
                     limits: np.ndarray | None = None) -> GroundTruth:
    """The ground truth of ``settings`` (a :class:`~.settings.Settings`) on ``positions``.

    The standard rule (frame window, strict radius, every frame a query) is
    :func:`compute_ground_truth`; otherwise revisit queries follow the
    per-query database ``limits`` (:func:`database_limits`) and ``exclude``
    holds the smallest frame gap any query is allowed (for the record).
    """
    if settings.standard:
        return compute_ground_truth(positions, settings.radius, settings.exclude,
                                    settings.distance, settings.pose_frame)
    if limits is None:
        limits = database_limits(len(positions), settings, times)
    coords = gt_coordinates(positions, settings.pose_frame, settings.distance)
    revisit = revisit_queries_within(coords, limits, settings.radius, settings.inclusive_radius)
    gaps = (np.arange(len(limits)) - limits)[limits >= 0]
    return GroundTruth(
        n_frames=len(coords), radius=float(settings.radius),
        exclude=int(gaps.min()) if len(gaps) else 0, distance=settings.distance,
        frame=settings.pose_frame, pairs=positive_pairs(coords, settings.radius),
        revisit=revisit, limits=np.asarray(limits, dtype=np.int64))


def pair_distances(positions: np.ndarray, i: np.ndarray, j: np.ndarray, frame: str,
                   distance: str) -> np.ndarray:
    """Ground-truth distances (metres) between frames ``i[k]`` and ``j[k]``."""
    coords = gt_coordinates(positions, frame, distance)
    return np.linalg.norm(coords[np.asarray(i)] - coords[np.asarray(j)], axis=1)
