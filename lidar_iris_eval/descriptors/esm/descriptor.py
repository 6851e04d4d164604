"""ESM (Tinchev, Penate-Sanchez and Fallon, RA-L 2019): learned segment descriptors.

Two modes (``source``):

* ``local-map`` (the default, the authors' setting: SegMap's pipeline with
  ESM's network and PROSAC): the pipeline builds the local map of every frame
  (:mod:`lidar_iris_eval.localmaps`, the scans of the last ``window`` frames,
  ``window`` = the evaluation's E); its segments are the frame's features
  (:mod:`.local_segments`), with persistent ids and an embedding cache
  (:mod:`.tracking`: ``describe`` = ``growth``, SegMap's rule, re-describes
  only segments that grew by ``growth`` = 10 %); a query is matched against the target map of the
  segments of every frame ``<= i - E`` (:mod:`.target_map`), which gives one
  matched frame and a 6-DoF pose;
* ``scan`` (preset ``single-scan``, not the authors' setting): each scan is
  segmented alone and matched frame against frame, as below.

The single-scan mode is a two-stage method (``descriptors/base.py``):

* **describe**: segments (:mod:`.segmentation`), each embedded in 16-d by the
  shipped network (:mod:`.network`, NumPy only) with a quality in [0, 1];
  the feature set is ``{"embedding": (S, 16), "quality": (S,), "centroids": (S, 3)}``;
* **retrieve**: each query segment takes its ``knn = 25`` nearest segments
  (squared L2) among the allowed frames; each neighbour votes for its frame
  with weight ``q_query * q_neighbour``; frames are ranked by their vote sum,
  and the retrieval distance is ``1 / (1 + votes)``;
* **verify**: the correspondences of a candidate frame are the (query segment,
  candidate segment) pairs of that k-NN, at most ``per_segment`` per query
  segment (its nearest ones in that frame); PROSAC
  (``matching.geometry.prosac_rigid``) on their centroids, sampled in
  decreasing ``q_query * q_candidate`` order, fits a rigid 6-DoF pose
  (candidate LiDAR frame -> query LiDAR frame) with inlier threshold
  ``inlier_threshold`` metres, at most ``iterations`` hypotheses (and at most
  10 per distinct triplet), stopping early at ``confidence``. The k-NN is
  the retrieval step's (frames allowed for the query); when :meth:`verify`
  is called alone, over the frames up to the latest candidate (never the
  query's own segments);
* **score** ("inverse inliers"): ``1 / (1 + n_inliers) + 1e-3 * mean inlier
  residual (m)``, smaller is better; ``inf`` when fewer than ``min_inliers``
  pairs agree.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor, Verification
from lidar_iris_eval.descriptors.esm import network, segmatch
from lidar_iris_eval.descriptors.esm.local_segments import local_map_clusters, sample_segment
from lidar_iris_eval.descriptors.esm.segmentation import SegmentParams, segment_scan
from lidar_iris_eval.descriptors.esm.target_map import (
    GROW_RULES,
    TARGET_VIEWS,
    Localisation,
    localise,
    target_lifetimes,
)
from lidar_iris_eval.descriptors.esm.tracking import DESCRIBE_RULES, SegmentTracker, content_digest
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.matching.geometry import prosac_rigid

_GROUND = ("auto", "labels", "height")
_SOURCES = ("local-map", "scan")
_SEGMENT_DESCRIPTORS = ("network", "segmatch")
#: the local-map window when no evaluation binds it to its E (the "paper" E, 30 frames)
DEFAULT_WINDOW = 30


@dataclass(frozen=True)
class ESMParams:
    """ESM settings (segmentation: SegMap defaults; matching: see the module docstring)."""

    max_range: float = 50.0
    ground: str = "auto"  # labels when the scan has them, else the height rule
    ground_z: float = -1.0
    voxel: float = 0.1
    radius: float = 0.2
    min_points: int = 100
    max_points: int = 15000
    seed: int = 0
    knn: int = 25
    per_segment: int = 3
    inlier_threshold: float = 0.6
    min_inliers: int = 3
    iterations: int = 300
    confidence: float = 0.99
    num_candidates: int = 10
    # the network: a file shipped in the package folder (by name) or a path; "" = esm_weights.npz
    weights: str = "esm_weights.npz"
    # local-map mode (SegMap's pipeline); see the module docstring
    source: str = "local-map"
    window: int = 0  # W frames per local map; 0 = the evaluation's E
    input_filter: str = "all"  # localmaps.filters: "segmap" (every 9th point) or "all"
    odometry: str = "gt"  # the poses that place scans: "gt" or "kiss-icp"
    map_radius: float = 50.0  # the local map's cylinder (m)
    dedup: float = 2.0  # target-map duplicate radius (m)
    target_view: str = "latest"  # which recent view of a segment the target keeps (target_map.py)
    consistency: float = 0.6  # centroid-consistency / inlier threshold (m)
    min_consistent: int = 6  # SegMap's minimum cluster size on accumulated maps
    grow: str = "order"  # a seed's consistent set: next member by PROSAC "order" or "degree"
    min_target: int = 50  # SegMap matches only once the target holds this many segments
    frame_rule: str = "estimate"  # matched frame: "estimate" or SegMap's "segments"
    max_offset: float = 4.0  # "estimate": reject when the nearest frame is farther (m)
    describe: str = "growth"  # embedding cache (tracking.py): "all", "exact" or SegMap's "growth"
    growth: float = 0.1  # "growth": re-describe at >= (1 + growth) x the voxels last described
    #: the segment descriptor: "network" (ESM's) or "segmatch" (SegMatch's seven eigenvalue
    #: features, :mod:`.segmatch`; preset ``segmatch``); the rest of the pipeline is shared
    segment_descriptor: str = "network"
    # local-map front end (local_segments.py; docs/esm.md "Front end on real scans"):
    ground_cell: float = 0.0  # local ground grid cell (m); 0 = only the input filter's rule
    ground_clearance: float = 0.3  # voxels up to this height above the local ground go (m)
    cluster_voxel: float = 0.0  # re-voxelise the map at this edge before clustering; 0 = off

    def __post_init__(self) -> None:
        for name, choices in (("source", _SOURCES), ("target_view", TARGET_VIEWS),
                              ("segment_descriptor", _SEGMENT_DESCRIPTORS),
                              ("describe", DESCRIBE_RULES), ("ground", _GROUND),
                              ("grow", GROW_RULES)):
            value = getattr(self, name)
            if value not in choices:
                raise LirisError(f"esm.{name}", f"must be one of {', '.join(choices)}, "
                                                f"got {value!r}")
        if int(self.window) < 0:
            raise LirisError("esm.window", "must be 0 (the evaluation's E) or positive")
        if self.frame_rule not in ("estimate", "segments"):
            raise LirisError("esm.frame_rule", "must be 'estimate' or 'segments', "
                                               f"got {self.frame_rule!r}")
        for name in ("ground_cell", "ground_clearance", "cluster_voxel"):
            if not getattr(self, name) >= 0:
                raise LirisError(f"esm.{name}", f"must be 0 or more, got {getattr(self, name)}")
        if self.cluster_voxel and self.cluster_voxel < self.voxel:
            raise LirisError("esm.cluster_voxel", f"must be 0 or at least esm.voxel "
                                                  f"({self.voxel} m), got {self.cluster_voxel}")
        if not self.growth >= 0:
            raise LirisError("esm.growth", f"must be 0 or more, got {self.growth}")
        if int(self.min_consistent) < 3:
            raise LirisError("esm.min_consistent", "a rigid fit needs at least 3 pairs")
        for name in ("knn", "per_segment", "min_inliers", "iterations", "num_candidates"):
            if int(getattr(self, name)) < 1:
                raise LirisError(f"esm.{name}", "must be at least 1")
        if self.min_inliers < 3:
            raise LirisError("esm.min_inliers", "a rigid fit needs at least 3 pairs")


@dataclass
class ESMDatabase:
    """All segments of a sequence, frame by frame (segments of frame i: offsets[i]:offsets[i+1])."""

    embedding: np.ndarray
    quality: np.ndarray
    centroids: np.ndarray
    offsets: np.ndarray
    frame_of: np.ndarray
    sq: np.ndarray = field(init=False)
    cache: dict = field(default_factory=dict)
    # local-map mode: world centroids, per-frame poses, target-map lifetimes
    world: np.ndarray | None = None
    poses: np.ndarray | None = None
    alive_until: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.sq = (self.embedding.astype(np.float64) ** 2).sum(1)

    def __len__(self) -> int:
        return len(self.offsets) - 1

    def rows(self, i: int) -> slice:
        return slice(int(self.offsets[i]), int(self.offsets[i + 1]))


class ESM(Descriptor):
    """ESM: segment, embed (16-d, NumPy), vote, verify with PROSAC."""

    name: ClassVar[str] = "esm"
    params_type: ClassVar[type] = ESMParams
    symmetric: ClassVar[bool] = False
    takes_scan: ClassVar[bool] = True
    two_stage: ClassVar[bool] = True

    def __init__(self, params: Any = None, preset: str = "custom"):
        super().__init__(params, preset)
        self._weights = None
        self.timing = {"segmentation": 0.0, "description": 0.0, "scans": 0,
                       "described": 0, "reused": 0}
        self.tracker = SegmentTracker(self.params.describe, self.params.growth)
        self._reused: float | None = None
        if self.local_map:  # the pipeline builds a local map per frame (extract.py)
            self.inputs = frozenset({"points", "local_map"})
        elif self.params.ground == "labels":
            self.inputs = frozenset({"points", "labels"})
        elif self.params.ground == "auto":  # labels where the scan has them, else the height rule
            self.optional_inputs = frozenset({"labels"})

    # ------------------------------------------------------------------ local maps

    @property
    def local_map(self) -> bool:
        """True in the local-map mode (SegMap's pipeline)."""
        return self.params.source == "local-map"

    @property
    def window(self) -> int:
        """W, the frames of one local map (``DEFAULT_WINDOW`` until an evaluation binds it)."""
        return int(self.params.window) or DEFAULT_WINDOW

    def bind_exclusion(self, exclude: int) -> ESM:
        """This descriptor with ``window`` set to the evaluation's E (when it is 0).

        A window larger than E would put database scans in a query's local map.
        """
        if not self.local_map:
            return self
        if exclude is None:  # a window in seconds (e.g. --convention logg3d)
            raise LirisError("--exclude", "ESM's local maps are the last E frames: give the "
                             "exclusion window in frames, or --preset single-scan")
        if self.params.window == 0:
            return type(self)(dataclasses.replace(self.params, window=int(exclude)), self.preset)
        if self.params.window > exclude:
            raise LirisError("esm.window", f"{self.params.window} frames is more than the "
                             f"exclusion window E = {exclude}: a query's local map would hold "
                             "database scans")
        return self

    def local_map_settings(self):
        """The :class:`~lidar_iris_eval.localmaps.LocalMapSettings` of this descriptor."""
        from lidar_iris_eval.localmaps import LocalMapSettings

        p = self.params
        return LocalMapSettings(window=self.window, voxel=p.voxel, radius=p.map_radius,
                                input_filter=p.input_filter, odometry=p.odometry)

    def run_info(self) -> dict[str, Any]:
        """The local maps (base class), the weights file and its checksum, the
        embedding-cache rule and its hit rate (metrics.json rows)."""
        info = {**super().run_info(), "weights": self.weights_path.name,
                "weights_sha256": self.cache_token()}
        if self.params.segment_descriptor == "segmatch":  # no network runs
            info.update(weights=None, weights_sha256=None, segment_descriptor="segmatch")
        if self.local_map:
            info["describe_rule"] = self.params.describe
            info["embedding_reuse_rate"] = (round(self._reused, 4) if self._reused is not None
                                            else None)
        return info

    # ------------------------------------------------------------------ describe

    @property
    def segment_params(self) -> SegmentParams:
        p = self.params
        _, arch = self.weights()
        return SegmentParams(p.max_range, p.ground_z, p.voxel, p.radius, p.min_points,
                             p.max_points, arch.n_points, p.seed, arch.norm_scale,
                             arch.align_yaw, p.ground_cell, p.ground_clearance,
                             p.cluster_voxel)

    @property
    def weights_path(self):
        """The weights file ``esm.weights`` names (:func:`network.resolve_weights`)."""
        return network.resolve_weights(self.params.weights)

    def weights(self) -> tuple[dict, network.Arch]:
        if self._weights is None:
            path = self.weights_path
            try:
                self._weights = network.load_weights(path)
            except (OSError, KeyError, ValueError) as err:
                raise self._unreadable_weights(path, err) from None
        return self._weights

    def cache_token(self) -> str:
        """SHA-256 (16 hex) of the weights file: part of the cache key (extract.py)."""
        path = self.weights_path
        try:
            return network.sha256_of(path)[:16]
        except OSError as err:
            raise self._unreadable_weights(path, err) from None

    def _unreadable_weights(self, path, err: Exception) -> LirisError:
        """The one error line for a weights file that cannot be read (names the parameter)."""
        return LirisError(f"esm.weights={self.params.weights}",
                          f"cannot read ESM weights {path} ({err})")

    def describe(self, scan: Any) -> dict[str, np.ndarray]:
        return self.compute(scan)

    def compute(self, scan: Any) -> dict[str, np.ndarray]:  # type: ignore[override]
        """Feature set of one scan (a Scan, or bare (N, 3+) points), or of one local map."""
        if self.local_map:
            return self.compute_local_map(scan)
        points = getattr(scan, "points", scan)
        labels = getattr(scan, "labels", None)
        if self.params.ground == "height":
            labels = None
        elif self.params.ground == "labels" and labels is None:
            raise LirisError("esm.ground", "is 'labels' but the scan has no labels")
        # per-thread CPU time: what one core spends, robust to a busy machine
        t0 = time.thread_time()
        segs = segment_scan(np.asarray(points)[:, :3], labels, self.segment_params)
        t1 = time.thread_time()
        emb, q = self.describe_segments(segs.points)
        t2 = time.thread_time()
        self.timing["segmentation"] += t1 - t0
        self.timing["description"] += t2 - t1
        self.timing["scans"] += 1
        return {"embedding": emb.astype(np.float32), "quality": q.astype(np.float64),
                "centroids": segs.centroids.astype(np.float64)}

    @property
    def embedding_dim(self) -> int:
        """Width of a segment descriptor: the network's output, or SegMatch's 7 features."""
        if self.params.segment_descriptor == "segmatch":
            return segmatch.DIM
        return int(self.weights()[1].fc[-1])

    def describe_segments(self, batch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(descriptors (S, D) float32, quality (S,))`` of resampled, normalised segments
        ((S, n_points, 3)): the network's embedding and quality, or SegMatch's features
        (:mod:`.segmatch`) with quality 1."""
        if self.params.segment_descriptor == "segmatch":
            return segmatch.describe_segments(list(batch))
        w, arch = self.weights()
        emb = network.embed(w, arch, batch)
        q = network.quality(w, emb) if len(emb) else np.zeros(0)
        return emb.astype(np.float32), np.asarray(q, np.float64)

    def begin_local_maps(self, start: int) -> None:
        """Start segment tracking afresh (called at the start of every extraction chunk)."""
        self.tracker.reset()

    def compute_local_map(self, frame: Any) -> dict[str, np.ndarray]:
        """Feature set of one :class:`~lidar_iris_eval.localmaps.LocalMapFrame`.

        ``centroids`` are in the frame's LiDAR frame, ``world`` in the world
        frame of the odometry, ``pose`` the frame's world-from-LiDAR pose,
        ``ids`` the persistent segment ids and ``described`` 1 where the
        network ran this frame, 0 where the embedding was reused
        (:mod:`.tracking`). Frames must come in order (a frame that does not
        follow the previous one starts tracking afresh).
        """
        if not hasattr(frame, "pose"):
            raise LirisError("esm.source", "is 'local-map' but was given a scan; use the "
                                           "single-scan preset (-d esm:single-scan) on scans")
        sp = self.segment_params
        t0 = time.thread_time()
        pts = np.asarray(frame.points, dtype=np.float64)
        keys = voxel_keys(frame, self.params.voxel)
        members = local_map_clusters(pts, sp)
        seg_keys = [keys[m] for m in members]
        ids = self.tracker.assign(int(frame.frame), seg_keys)
        world = np.array([pts[m].mean(axis=0) for m in members]).reshape(-1, 3)
        sizes = np.array([len(m) for m in members], np.int64)
        t1 = time.thread_time()
        n = len(members)
        emb = np.zeros((n, self.embedding_dim), np.float32)
        q = np.zeros(n, np.float64)
        fresh = np.zeros(n, np.int8)
        # content digests only decide reuse under ``exact`` (tracking.py)
        exact = self.params.describe == "exact"
        digests = [content_digest(seg_keys[s], pts[members[s]]) if exact else b""
                   for s in range(n)]
        for s in range(n):
            hit = self.tracker.lookup(ids[s], int(sizes[s]), digests[s])
            if hit is None:
                fresh[s] = 1
            else:
                emb[s], q[s] = hit
        todo = np.nonzero(fresh)[0]
        if len(todo):
            if self.params.segment_descriptor == "segmatch":  # every voxel of the segment
                emb[todo], q[todo] = segmatch.describe_segments([pts[members[s]] for s in todo])
            else:
                batch = np.stack([sample_segment(pts[members[s]], seg_keys[s], sp)
                                  for s in todo])
                emb[todo], q[todo] = self.describe_segments(batch)
            for s in todo:
                self.tracker.store(ids[s], int(sizes[s]), digests[s], emb[s], q[s])
        self.tracker.forget_ended(ids)
        t2 = time.thread_time()
        self.timing["segmentation"] += t1 - t0
        self.timing["description"] += t2 - t1
        self.timing["scans"] += 1
        self.timing["described"] += int(len(todo))
        self.timing["reused"] += int(n - len(todo))
        pose = np.asarray(frame.pose, dtype=np.float64)
        inv = np.linalg.inv(pose)
        local = world @ inv[:3, :3].T + inv[:3, 3] if len(world) else np.zeros((0, 3))
        return {"embedding": emb.astype(np.float32), "quality": q.astype(np.float64),
                "centroids": local.astype(np.float64), "world": world.astype(np.float64),
                "sizes": sizes, "pose": pose.reshape(1, 4, 4), "ids": ids.astype(np.int64),
                "described": fresh}

    # ------------------------------------------------------------------ stage 1

    def prepare(self, features: Any) -> ESMDatabase:
        n = len(features)
        frames = [features[i] for i in range(n)]
        sizes = np.array([len(f["quality"]) for f in frames], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

        def flat(key, dtype, width):
            parts = [np.asarray(f[key], dtype=dtype).reshape(-1, width) for f in frames]
            return np.concatenate(parts) if parts else np.zeros((0, width), dtype)

        db = ESMDatabase(
            embedding=flat("embedding", np.float32, self.embedding_dim),
            quality=flat("quality", np.float64, 1)[:, 0],
            centroids=flat("centroids", np.float64, 3), offsets=offsets,
            frame_of=np.repeat(np.arange(n), sizes),
        )
        if self.local_map:
            if frames and "world" not in frames[0]:
                raise LirisError("esm.source", "'local-map' needs features of local maps")
            if frames and "described" in frames[0] and len(db.quality):
                self._reused = 1.0 - float(flat("described", np.int64, 1).mean())
            db.world = flat("world", np.float64, 3)
            db.poses = flat("pose", np.float64, 16).reshape(-1, 4, 4)
            db.alive_until = target_lifetimes(db.world, db.frame_of, n, self.params.dedup,
                                              self.window, flat("sizes", np.int64, 1)[:, 0],
                                              self.params.target_view)
        return db

    def localisation(self, db: ESMDatabase, query: int, n_allowed: int) -> Localisation:
        """The query's local map against the target of frames ``[0, n)``, ``n <= i - W + 1``."""
        p = self.params
        n = min(int(n_allowed), int(query) - self.window + 1, len(db))
        key = ("loc", int(query), n)
        if key in db.cache:
            return db.cache[key]
        loc = Localisation(-1, np.full((4, 4), np.nan), 0, float("nan"), 0)
        if n > 0:
            t = np.nonzero((db.frame_of < n) & (db.alive_until >= n))[0]
            q = db.rows(int(query))
            if len(t) >= p.min_target and q.stop > q.start:
                loc = localise(db.embedding[q], db.quality[q], db.centroids[q],
                               db.embedding[t], db.quality[t], db.world[t], t,
                               db.poses[:n, :3, 3], knn=p.knn, threshold=p.consistency,
                               min_consistent=p.min_consistent, iterations=p.iterations,
                               frame_rule=p.frame_rule, max_offset=p.max_offset,
                               grow=p.grow)
        db.cache.clear()
        db.cache[key] = loc
        return loc

    def segment_knn(self, db: ESMDatabase, query: int, n_allowed: int):
        """Each query segment's ``knn`` nearest segments in frames ``[0, n_allowed)``."""
        key = (query, n_allowed)
        if key in db.cache:
            return db.cache[key]
        q = db.rows(query)
        m = int(db.offsets[min(n_allowed, len(db))])
        eq = db.embedding[q].astype(np.float64)
        if m == 0 or len(eq) == 0:
            out = (np.zeros((len(eq), 0), np.int64), np.zeros((len(eq), 0)))
        else:
            d2 = db.sq[q][:, None] + db.sq[None, :m] - 2.0 * eq @ db.embedding[:m].T
            d2[:, q.start:min(q.stop, m)] = np.inf  # never the query's own segments
            k = min(self.params.knn, m)
            nn = np.argpartition(d2, k - 1, axis=1)[:, :k]
            dd = np.take_along_axis(d2, nn, axis=1)
            order = np.argsort(dd, axis=1, kind="stable")
            dd = np.maximum(np.take_along_axis(dd, order, 1), 0.0)
            out = (np.take_along_axis(nn, order, 1), dd)
        db.cache.clear()
        db.cache[key] = out
        return out

    def retrieve(self, db: ESMDatabase, query: int, n_allowed: int, k: int):
        """Frames ranked by quality-weighted votes of the segments' k-NN.

        In the local-map mode: the one frame the target-map match gives (none
        when it is rejected); frames later than ``query - W`` are never allowed.
        """
        if self.local_map:
            loc = self.localisation(db, query, n_allowed)
            if loc.frame < 0:
                return np.zeros(0, np.int64), np.zeros(0)
            return np.array([loc.frame], np.int64), np.array([1.0 / (1.0 + loc.inliers)])
        nn, _ = self.segment_knn(db, query, n_allowed)
        if nn.size == 0:
            return np.zeros(0, np.int64), np.zeros(0)
        qq = db.quality[db.rows(query)]
        weight = (qq[:, None] * db.quality[nn]).ravel()
        votes = np.bincount(db.frame_of[nn.ravel()], weights=weight, minlength=n_allowed)
        voted = np.nonzero(votes > 0)[0]
        best = voted[np.lexsort((voted, -votes[voted]))][:k]
        return best.astype(np.int64), 1.0 / (1.0 + votes[best])

    # ------------------------------------------------------------------ stage 2

    def correspondences(self, db: ESMDatabase, query: int, cand: int, n_allowed: int):
        """(query rows, candidate rows, quality products) of one candidate frame."""
        nn, dd = self.segment_knn(db, query, n_allowed)
        qrows = np.arange(db.offsets[query], db.offsets[query + 1])
        in_frame = db.frame_of[nn] == cand if nn.size else np.zeros(nn.shape, bool)
        # per query segment, its nearest ``per_segment`` neighbours inside the frame
        rank = np.cumsum(in_frame, axis=1)
        keep = in_frame & (rank <= self.params.per_segment)
        a, col = np.nonzero(keep)
        b = nn[a, col]
        qa = qrows[a]
        return qa, b, db.quality[qa] * db.quality[b]

    def verify(self, db: ESMDatabase, query: int, candidates: np.ndarray) -> Verification:
        candidates = np.asarray(candidates, dtype=np.int64).reshape(-1)
        p = self.params
        k = len(candidates)
        score = np.full(k, np.inf)
        pose = np.tile(np.full((4, 4), np.nan), (k, 1, 1))
        inliers = np.zeros(k, np.int64)
        if self.local_map:
            cached = [key for key in db.cache if key[0] == "loc" and key[1] == query]
            n = cached[0][2] if cached else (int(candidates.max()) + 1 if k else 0)
            loc = self.localisation(db, query, n)
            for c, cand in enumerate(candidates):
                if loc.frame >= 0 and int(cand) == loc.frame:
                    score[c] = 1.0 / (1.0 + loc.inliers) + 1e-3 * loc.residual
                    pose[c] = loc.world_to_query @ db.poses[loc.frame]
                    inliers[c] = loc.inliers
            return Verification(score=score, pose=pose, inliers=inliers)
        # the k-NN of the retrieval step, or (verify alone) over frames up to the last candidate
        cached = [key for key in db.cache if key[0] == query]
        n_allowed = cached[0][1] if cached else (int(candidates.max()) + 1 if k else 0)
        for c, cand in enumerate(candidates):
            qa, b, prod = self.correspondences(db, query, int(cand), n_allowed)
            if len(qa) < p.min_inliers:
                continue
            order = np.lexsort((np.arange(len(prod)), -prod))
            rng = np.random.default_rng([p.seed, int(query), int(cand)])
            n = len(qa)
            iters = int(min(p.iterations, 10 * n * (n - 1) * (n - 2) // 6))
            res = prosac_rigid(db.centroids[b], db.centroids[qa], order,
                               threshold=p.inlier_threshold, iterations=iters,
                               min_inliers=p.min_inliers, rng=rng, confidence=p.confidence)
            n_in = int(res.n_inliers)
            inliers[c] = n_in
            if res.success and n_in >= p.min_inliers:
                resid = float(np.mean(res.residuals[res.inliers]))
                score[c] = 1.0 / (1.0 + n_in) + 1e-3 * resid
                pose[c] = res.pose
        return Verification(score=score, pose=pose, inliers=inliers)

    def retrieval_pairwise(self, db: ESMDatabase, rows: np.ndarray, cols) -> np.ndarray:
        """Retrieval distance ``1 / (1 + votes)`` of frames ``rows`` against frames ``cols``.

        Votes here count each query segment's k-NN over *all* frames of ``cols``.
        """
        cols = np.arange(len(db))[cols] if isinstance(cols, slice) else np.asarray(cols)
        out = np.ones((len(rows), len(cols)))
        col_rows = np.concatenate([np.arange(db.offsets[c], db.offsets[c + 1]) for c in cols]) \
            if len(cols) else np.zeros(0, np.int64)
        if len(col_rows) == 0:
            return out
        pos = -np.ones(len(db), np.int64)
        pos[cols] = np.arange(len(cols))
        e = db.embedding[col_rows].astype(np.float64)
        for r, i in enumerate(rows):
            q = db.rows(int(i))
            if q.stop == q.start:
                continue
            d2 = db.sq[q][:, None] + db.sq[col_rows][None, :] - 2.0 * db.embedding[q] @ e.T
            k = min(self.params.knn, len(col_rows))
            nn = np.argpartition(d2, k - 1, axis=1)[:, :k]
            w = (db.quality[q][:, None] * db.quality[col_rows[nn]]).ravel()
            votes = np.bincount(pos[db.frame_of[col_rows[nn.ravel()]]], weights=w,
                                minlength=len(cols))
            out[r] = 1.0 / (1.0 + votes)
        return out


def voxel_keys(frame: Any, voxel: float) -> np.ndarray:
    """The voxel key of every point of a local map (``frame.keys``, or from its centroids).

    A voxel centroid in millimetres lies within its voxel (its points were
    rounded to millimetres first), so ``floor((x_mm + 0.5) / voxel_mm)`` is its
    voxel index without rounding trouble at the faces.
    """
    keys = getattr(frame, "keys", None)
    if keys is not None:
        return np.asarray(keys, dtype=np.int64)
    from lidar_iris_eval.localmaps.grid import encode

    voxel_mm = int(round(voxel * 1000))
    mm = np.asarray(frame.points, dtype=np.float64) * 1000.0
    return encode(np.floor((mm + 0.5) / voxel_mm).astype(np.int64))
