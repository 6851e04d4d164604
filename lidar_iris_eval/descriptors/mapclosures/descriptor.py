"""MapClosures (Gupta et al., ICRA 2024; PRBonn ``map-closures`` 2.2.0) as a two-stage method.

MapClosures detects loop closures between **local maps**: it aligns a map to
its ground plane, projects it to a bird's-eye-view density image
(``density_map_resolution`` m pixels, densities below ``density_threshold``
zeroed), extracts ORB features, matches them to every earlier map in a
Hamming binary search tree (HBST, ``hamming_distance_threshold``), and
verifies a candidate map by 2-D RANSAC (3 m inlier distance), which gives a
2-D rigid transform and an inlier count. All of that is the authors' C++, run
through their Python package; liris only builds the input and reads the
result.

In liris the method runs per frame:

* **input** (:mod:`.localmap`): the local map at frame ``i``, built from the
  scans of frames ``i - window < j <= i`` placed with the sequence's poses,
  within a ``radius`` cylinder, in MapClosures' voxel map; the extraction
  stage only thins each scan (cached), the maps are built in :meth:`prepare`;
* **retrieval + verification** (:meth:`prepare`): frame ``i``'s map is given
  to ``MapClosures.get_closures(i, map)`` in frame order, exactly as its
  pipeline feeds maps; that call adds the map to the database and returns
  every verified earlier map ``j < i - 3`` (the C++ skips the 3 most recent
  maps) with more than 2 inliers. liris keeps the whole list;
* **protocol 1** respects E by filtering that list to ``j <= i - E``
  (:meth:`retrieve`), then takes the candidate with most inliers. The
  database the HBST search runs in also holds frames ``i - E < j < i``; they
  can change how the tree splits (an approximate search), never a
  verification, and they are never matched;
* **score**: ``-inliers`` (smaller is better, as every liris distance), so a
  PR threshold of ``-t`` accepts matches with at least ``t`` inliers;
  MapClosures' own pipeline accepts ``inliers > inliers_threshold`` (5);
* **pose**: the closure's 4x4 ``pose``, which the C++ builds as
  ``G_i^-1 [R2 t2; 0 1] G_j`` from the 2-D RANSAC transform ``(R2, t2)``
  (lifted to SE(3) with no z rotation or z translation) and the ground
  alignments ``G`` of both maps. Each map is in the LiDAR frame of its frame,
  so the pose maps points of frame ``j``'s LiDAR frame into frame ``i``'s: the
  liris convention (checked in tests/test_mapclosures.py);
* **protocol 2**: a pair ``(i, j)`` is scored when either frame's call
  verified the other (``j < i - 3`` when ``i`` was queried, or the reverse);
  each frame's top-``num_candidates`` by inliers are kept.

The C++ RANSAC draws its samples from ``std::random_device``: inlier counts
may differ by a few between two runs of the same command, which no seed
from Python can fix (docs/mapclosures.md).
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np
from tqdm import tqdm

from lidar_iris_eval.descriptors.base import Descriptor, Verification
from lidar_iris_eval.descriptors.mapclosures import backend
from lidar_iris_eval.descriptors.mapclosures.localmap import (
    LocalMapSettings,
    frame_local_map,
    thin_scan,
)
from lidar_iris_eval.errors import LirisError

#: MapClosures' C++ (MapClosures.cpp): maps this recent are never candidates
MAPS_SKIPPED = 3


@dataclass(frozen=True)
class MapClosuresParams:
    """MapClosures parameters; presets in ``lidar_iris_eval/descriptors/mapclosures/presets.yaml``.

    MapClosures' own (``config/basic_config.yaml`` of PRBonn/MapClosures):
    ``density_map_resolution`` m, ``density_threshold``,
    ``hamming_distance_threshold`` bits, ``inliers_threshold`` (its pipeline's
    acceptance, reported as an operating point; the PR sweep covers all).

    Local maps (liris, the rule shared with ESM): ``window`` frames (must not
    exceed protocol 1's E), ``radius`` m cylinder, ``voxel`` m voxel map
    (MapClosures' pipeline uses its density resolution), ``odometry`` ``gt``.

    ``num_candidates``: protocol 2 keeps each frame's best this many.
    """

    density_map_resolution: float = 0.5
    density_threshold: float = 0.05
    hamming_distance_threshold: int = 50
    inliers_threshold: int = 5
    window: int = 30
    radius: float = 50.0
    voxel: float = 0.5
    odometry: str = "gt"
    num_candidates: int = 10

    def __post_init__(self) -> None:
        for key in ("density_map_resolution", "radius", "voxel"):
            if not getattr(self, key) > 0:
                raise LirisError(f"mapclosures.{key}",
                                 f"must be positive, got {getattr(self, key)}")
        if not 0 <= self.density_threshold < 1:
            raise LirisError("mapclosures.density_threshold",
                             f"must be in [0, 1), got {self.density_threshold}")
        for key in ("hamming_distance_threshold", "window", "num_candidates"):
            if getattr(self, key) < 1:
                raise LirisError(f"mapclosures.{key}", f"must be at least 1, got "
                                 f"{getattr(self, key)}")
        if self.odometry != "gt":
            raise LirisError("mapclosures.odometry", f"{self.odometry!r}: only 'gt' (the "
                             "sequence's poses) is implemented")

    def local_maps(self) -> LocalMapSettings:
        """The local-map settings."""
        return LocalMapSettings(self.window, self.radius, self.voxel, self.odometry)

    def closure_config(self) -> dict:
        """MapClosures' own configuration (``MapClosuresConfig`` fields)."""
        return {"density_map_resolution": self.density_map_resolution,
                "density_threshold": self.density_threshold,
                "hamming_distance_threshold": self.hamming_distance_threshold,
                "inliers_threshold": self.inliers_threshold}


@dataclass
class ClosureTable:
    """Every verified pair of one sequence, as MapClosures returned it.

    ``query[k]`` was verified against ``ref[k] < query[k] - 3`` with
    ``inliers[k]`` inliers and ``pose[k]`` (ref's LiDAR frame -> query's).
    """

    n: int
    query: np.ndarray
    ref: np.ndarray
    inliers: np.ndarray
    pose: np.ndarray
    map_points: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    seconds: dict = field(default_factory=dict)

    def by_query(self, i: int) -> np.ndarray:
        """Rows verified when frame ``i`` was queried."""
        return np.flatnonzero(self.query == i)


class MapClosures(Descriptor):
    """MapClosures on per-frame local maps (module docstring)."""

    name: ClassVar[str] = "mapclosures"
    label: ClassVar[str] = "MapClosures"
    params_type: ClassVar[type] = MapClosuresParams
    two_stage: ClassVar[bool] = True
    warm_up: ClassVar[bool] = False

    def __init__(self, params: Any = None, preset: str = "custom"):
        backend.require(self.name)
        super().__init__(params, preset)
        self._poses: np.ndarray | None = None
        #: (features, table) of the sequences already matched: protocols 1 and 2
        #: read one run of MapClosures (its RANSAC is not seeded; two runs differ)
        self._prepared: list[tuple[Any, ClosureTable]] = []

    # ------------------------------------------------------------ inputs
    def check_inputs(self, sequence: Any) -> None:
        """Check inputs and keep the sequence's LiDAR-frame poses for the local maps."""
        super().check_inputs(sequence)
        poses = getattr(sequence, "poses", None)
        if poses is None:
            raise LirisError(getattr(sequence, "path", self.name),
                             f"{self.name} builds local maps from poses; this input has none")
        self.bind_poses(poses)

    def bind_poses(self, poses: np.ndarray) -> None:
        """Use ``poses`` (``(N, 4, 4)`` LiDAR frame) to place the scans of the local maps."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 3 or poses.shape[1:] != (4, 4):
            raise ValueError(f"poses must be (N, 4, 4), got {poses.shape}")
        self._poses = poses
        self._prepared = []

    def compute(self, points: np.ndarray) -> dict[str, np.ndarray]:
        """One scan thinned by MapClosures' voxel map: ``{"points": (K, 3) float32}``."""
        return {"points": thin_scan(points, self.params.voxel)}

    def run_info(self) -> dict[str, Any]:
        """The local maps this run used, and where the matching time went (metrics.json)."""
        lm = self.params.local_maps()
        info: dict[str, Any] = {
            "local_map_builder": "map_closures VoxelMap of frames i-window<j<=i "
                                 "(descriptors/mapclosures/localmap.py)",
            "local_map_window": lm.window, "local_map_radius_m": lm.radius,
            "local_map_voxel_m": lm.voxel, "local_map_odometry": lm.odometry,
            "map_closures_version": backend.installed_version(),
        }
        if self._prepared:
            # the run's own table: the pipeline's two-frame warm-up may have come last
            table = max((t for _, t in self._prepared), key=lambda t: t.n)
            info["local_maps"] = int(len(table.map_points))
            info["local_map_points_median"] = (float(np.median(table.map_points))
                                               if len(table.map_points) else None)
            info["local_maps_s"] = table.seconds.get("local_maps")
            info["map_closures_s"] = table.seconds.get("map_closures")
        return info

    # ------------------------------------------------------------ matching
    def prepare(self, features: Any) -> ClosureTable:
        """Run MapClosures over the local maps of every frame, in frame order (once)."""
        n = len(features)
        if self._poses is None or len(self._poses) < n:
            raise LirisError(self.name, "needs the sequence's poses before matching "
                             "(evaluate through liris eval, or call bind_poses)")
        for seen, table in self._prepared:
            if seen is features:
                return table
        table = run_closures(features, self._poses[:n], self.params)
        self._prepared = [*self._prepared[-2:], (features, table)]
        return table

    def _check_window(self, db: ClosureTable, query: int, n_allowed: int) -> None:
        """A LirisError when protocol 1's E is shorter than the local maps' window.

        E is ``query - n_allowed + 1`` (the pipeline allows frames ``<= i - E``);
        the pipeline's untimed warm-up on two frames is not checked.
        """
        exclude = query - n_allowed + 1
        if db.n > 2 and 0 < n_allowed <= query and exclude < self.params.window:
            raise LirisError(
                "mapclosures.window",
                f"local maps span {self.params.window} frames but protocol 1's exclusion "
                f"window is {exclude}: a query's map would hold database scans; use "
                f"--param mapclosures.window={exclude} or a larger --exclude")

    def retrieve(self, db: ClosureTable, query: int, n_allowed: int, k: int
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Verified frames of ``query`` in ``[0, n_allowed)``, most inliers first.

        Protocol 1 (``n_allowed <= query``): the closures found when ``query``
        was matched, filtered to the allowed frames. Protocol 2
        (``n_allowed > query``): closures found in either direction.
        """
        self._check_window(db, query, n_allowed)
        rows = db.by_query(query)
        other = db.ref[rows]
        inl = db.inliers[rows]
        if n_allowed > query:
            back = np.flatnonzero(db.ref == query)
            other = np.concatenate([other, db.query[back]])
            inl = np.concatenate([inl, db.inliers[back]])
        keep = other < n_allowed
        other, inl = other[keep], inl[keep]
        order = np.lexsort((other, -inl))[:k]
        return other[order].astype(np.int64), -inl[order].astype(np.float64)

    def default_candidates(self) -> int:
        """Protocol 2 keeps each frame's ``num_candidates`` best closures."""
        return int(self.params.num_candidates)

    def verify(self, db: ClosureTable, query: int, candidates: np.ndarray) -> Verification:
        """Score ``-inliers`` and pose of each candidate, as MapClosures verified it."""
        candidates = np.asarray(candidates, dtype=np.int64)
        k = len(candidates)
        score = np.full(k, np.inf)
        pose = np.full((k, 4, 4), np.nan)
        inliers = np.zeros(k, np.int64)
        fwd = db.by_query(query)
        back = np.flatnonzero(db.ref == query)
        for c, j in enumerate(candidates):
            hit = fwd[db.ref[fwd] == j]
            if len(hit):
                r = int(hit[0])
                pose[c] = db.pose[r]
            else:
                hit = back[db.query[back] == j]
                if not len(hit):
                    continue
                r = int(hit[0])
                pose[c] = np.linalg.inv(db.pose[r])  # verified the other way round
            inliers[c] = db.inliers[r]
            score[c] = -float(db.inliers[r])
        return Verification(score, pose, inliers)


def run_closures(features: Any, poses: np.ndarray, params: MapClosuresParams,
                 progress: bool = True) -> ClosureTable:
    """Feed each frame's local map to MapClosures in frame order; every verified pair.

    ``features[i]["points"]`` are frame ``i``'s thinned points (LiDAR frame).
    """
    closer = backend.closer(params.closure_config())
    settings = params.local_maps()
    n = len(features)
    scans = [np.asarray(features[i]["points"]) for i in range(n)]
    query, ref, inliers, pose, sizes = [], [], [], [], np.zeros(n, np.int64)
    t_map = t_close = 0.0
    # the pipeline does not tell a method about --quiet: a bar only on a terminal
    for i in tqdm(range(n), desc="mapclosures local maps", unit="frame", leave=False,
                  file=sys.stderr, disable=None if progress and n >= 50 else True):
        t0 = time.perf_counter()
        local_map = frame_local_map(scans, poses, i, settings)
        t1 = time.perf_counter()
        sizes[i] = len(local_map)
        for closure in closer.get_closures(i, local_map):
            if closure.target_id != i:  # the C++ always reports the query as target
                raise RuntimeError(f"map_closures returned target {closure.target_id} for {i}")
            query.append(i)
            ref.append(closure.source_id)
            inliers.append(closure.number_of_inliers)
            pose.append(np.asarray(closure.pose, dtype=np.float64))
        t_close += time.perf_counter() - t1
        t_map += t1 - t0
    return ClosureTable(
        n=n, query=np.asarray(query, np.int64), ref=np.asarray(ref, np.int64),
        inliers=np.asarray(inliers, np.int64),
        pose=np.asarray(pose, np.float64).reshape(-1, 4, 4), map_points=sizes,
        seconds={"local_maps": t_map, "map_closures": t_close})
