"""GOSMatch (Zhu et al., IROS 2020): graph-of-semantics loop closure, two stages.

A scan becomes a set of objects (vehicles, trunks, poles), either given (the
authors' released front-end output, :mod:`lidar_iris_eval.io.objects`) or
clustered from per-point SemanticKITTI labels (:mod:`.semantics`). From their
centroids:

* stage 1, **retrieval**: the 366-d graph descriptor (edge-length histograms,
  :func:`.graph.graph_descriptor`); exact k-NN (k-d trees) among the allowed
  frames gives ``candidates`` frames;
* stage 2, **verification**: 183-d vertex descriptors, same-class nearest
  neighbours, RANSAC + SVD pose, a named score (:mod:`.verification`).

Per scan the method stores a feature set (a dict of arrays whose first
dimension is the number of objects K)::

    {"graph": (366,) float64, "centroids": (K, 3) float64,
     "classes": (K,) int8, "vertex": (K, 183) float32}
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.gosmatch.graph import (
    EDGE_TYPES,
    N_CLASSES,
    check_sorted,
    graph_descriptor,
    vertex_descriptors,
)
from lidar_iris_eval.descriptors.gosmatch.kernels import SCORE_CODES, verify_query
from lidar_iris_eval.descriptors.gosmatch.retrieval import PrefixKNN, l2_block
from lidar_iris_eval.descriptors.gosmatch.semantics import ClusterSettings, objects_from_labels
from lidar_iris_eval.descriptors.gosmatch.verification import (
    SCORES,
    VerifySettings,
    verify_pair,
)
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.matching.geometry import yaw_deg_of

try:  # the two-stage result type of the pipeline
    from lidar_iris_eval.descriptors.base import Verification
except ImportError:  # pragma: no cover - only before the pipeline defines it
    from typing import NamedTuple

    class Verification(NamedTuple):  # type: ignore[no-redef]
        score: np.ndarray
        pose: np.ndarray
        inliers: np.ndarray


@dataclass(frozen=True)
class GOSMatchParams:
    """GOSMatch parameters; presets in ``lidar_iris_eval/descriptors/gosmatch/presets.yaml``.

    Descriptors (authors' code): ``bins`` x ``bin_width`` m; ``graph_pairs``
    ``ordered`` (code: ordered pairs + self-pairs in same-class blocks) or
    ``unordered`` (paper); ``vertex_offset`` ``cumcount-bug`` (code) or ``exact``.

    Front end (labels only; in neither code nor paper, chosen on simulated
    sequences): ``cluster_tolerance`` m, ``cluster_min_points``, objects within
    ``max_range`` m, ``traffic_signs`` adds class 81 to the poles.

    Matching (in neither code nor paper, chosen on simulated sequences):
    ``candidates`` N retrieved per query, ``ransac_iterations``,
    ``inlier_threshold`` m, ``min_inliers``, ``score`` (``clipped-mean`` or
    ``inlier-mean``), ``seed`` of RANSAC.
    """

    graph_pairs: str = "ordered"
    vertex_offset: str = "cumcount-bug"
    bins: int = 61
    bin_width: float = 1.0
    cluster_tolerance: float = 0.5
    cluster_min_points: int = 10
    max_range: float = 50.0
    traffic_signs: bool = False
    candidates: int = 10
    ransac_iterations: int = 100
    inlier_threshold: float = 1.0
    min_inliers: int = 4
    score: str = "clipped-mean"
    seed: int = 0

    def __post_init__(self) -> None:
        checks = {
            "graph_pairs": (self.graph_pairs, ("ordered", "unordered")),
            "vertex_offset": (self.vertex_offset, ("cumcount-bug", "exact")),
            "score": (self.score, SCORES),
        }
        for key, (value, allowed) in checks.items():
            if value not in allowed:
                raise LirisError(f"gosmatch.{key}", f"{value!r} is not one of {', '.join(allowed)}")
        positive = {
            "bins": self.bins, "bin_width": self.bin_width,
            "cluster_tolerance": self.cluster_tolerance, "max_range": self.max_range,
            "candidates": self.candidates, "ransac_iterations": self.ransac_iterations,
            "inlier_threshold": self.inlier_threshold,
        }
        for key, value in positive.items():
            if not value > 0:
                raise LirisError(f"gosmatch.{key}", f"must be positive, got {value}")
        if self.min_inliers < 3:
            raise LirisError("gosmatch.min_inliers", f"must be at least 3, got {self.min_inliers}")


@dataclass
class GOSMatchDB:
    """What :meth:`GOSMatch.prepare` builds once per sequence.

    The objects of all frames are stored flat: frame ``i`` owns rows
    ``offsets[i]:offsets[i + 1]`` of ``centroids``, ``classes`` and ``vertex``.
    """

    graph: np.ndarray
    knn: PrefixKNN
    offsets: np.ndarray
    centroids: np.ndarray
    classes: np.ndarray
    vertex: np.ndarray

    def __len__(self) -> int:
        return len(self.graph)

    def frame(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centroids, classes and vertex descriptors of frame ``i``."""
        a, b = self.offsets[i], self.offsets[i + 1]
        return self.centroids[a:b], self.classes[a:b], self.vertex[a:b]


class GOSMatch(Descriptor):
    """GOSMatch: semantic-object graphs, retrieval then geometric verification."""

    name: ClassVar[str] = "gosmatch"
    params_type: ClassVar[type] = GOSMatchParams
    symmetric: ClassVar[bool] = False
    #: reads labelled points (clustered here) or given objects: ANY ONE of the two
    inputs: ClassVar[frozenset[str]] = frozenset({"labels", "objects"})
    inputs_any: ClassVar[bool] = True
    takes_scan: ClassVar[bool] = True
    two_stage: ClassVar[bool] = True

    # ------------------------------------------------------------------ stage 0

    @property
    def cluster_settings(self) -> ClusterSettings:
        p = self.params
        return ClusterSettings(p.cluster_tolerance, p.cluster_min_points, p.max_range,
                               p.traffic_signs)

    @property
    def verify_settings(self) -> VerifySettings:
        p = self.params
        return VerifySettings(p.ransac_iterations, p.inlier_threshold, p.min_inliers, p.score)

    def objects(self, scan: Any) -> tuple[np.ndarray, np.ndarray]:
        """Centroids and class codes of a scan: given objects, or clustered labels."""
        if hasattr(scan, "centroids") and hasattr(scan, "classes"):
            centroids = np.asarray(scan.centroids, dtype=np.float64).reshape(-1, 3)
            classes = np.asarray(scan.classes, dtype=np.int8)
            check_sorted(classes)
            return centroids, classes
        labels = getattr(scan, "labels", None)
        if labels is None:
            raise LirisError(
                "gosmatch", "needs per-point SemanticKITTI labels (labels/NNNNNN.label beside "
                            "the scans) or the authors' objects (bow.txt + centroids/)"
            )
        return objects_from_labels(scan.points, labels, self.cluster_settings)

    def check_inputs(self, sequence: Any) -> None:
        """The sequence must provide labels (clustered here) or objects: either will do."""
        provides = set(getattr(sequence, "provides", {"points", "intensity"}))
        if provides & self.inputs:
            return
        where = getattr(sequence, "labels_dir", None)
        source = where if where is not None else getattr(sequence, "path", self.name)
        raise LirisError(
            source, f"{self.name} needs per-point SemanticKITTI labels "
                    f"({'no .label files here' if where is not None else 'none in this input'}) "
                    "or an object layout (bow.txt + centroids/)"
        )

    def describe(self, scan: Any) -> dict[str, np.ndarray]:
        """The feature set of a scan as the pipeline reads it (object scan or labelled scan)."""
        return self.compute(scan)

    def features(self, centroids: np.ndarray, classes: np.ndarray) -> dict[str, np.ndarray]:
        """The feature set of one scan from its (class-sorted) objects."""
        p = self.params
        graph = graph_descriptor(centroids, classes, p.graph_pairs, p.bins, p.bin_width)
        vertex = vertex_descriptors(centroids, classes, p.vertex_offset, p.bins, p.bin_width)
        return {
            "graph": graph,
            "centroids": np.ascontiguousarray(centroids, dtype=np.float64).reshape(-1, 3),
            "classes": np.ascontiguousarray(classes, dtype=np.int8),
            "vertex": vertex,
        }

    def compute(self, scan: Any) -> dict[str, np.ndarray]:  # type: ignore[override]
        """The feature set of a scan (an object scan, or a Scan with labels)."""
        return self.features(*self.objects(scan))

    @property
    def graph_size(self) -> int:
        return len(EDGE_TYPES) * self.params.bins

    @property
    def vertex_size(self) -> int:
        return N_CLASSES * self.params.bins

    # ------------------------------------------------------------------ stage 1

    def prepare(self, features: Any) -> GOSMatchDB:
        """Stack the graph descriptors and keep each frame's objects for verification."""
        n = len(features)
        frames = [features[i] for i in range(n)]
        if hasattr(features, "stacked"):
            graph = np.asarray(features.stacked("graph"), dtype=np.float64)
        else:
            graph = np.stack([f["graph"] for f in frames]).astype(np.float64, copy=False)
        graph = graph.reshape(n, -1)
        sizes = np.array([len(f["classes"]) for f in frames], dtype=np.int64)
        offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)

        def flat(key: str, dtype, width: int) -> np.ndarray:
            parts = [np.asarray(f[key], dtype=dtype).reshape(-1, width) for f in frames]
            return np.ascontiguousarray(np.concatenate(parts) if parts else
                                        np.empty((0, width), dtype))

        return GOSMatchDB(
            graph=graph,
            knn=PrefixKNN(graph),
            offsets=offsets,
            centroids=flat("centroids", np.float64, 3),
            classes=flat("classes", np.int8, 1).reshape(-1),
            vertex=flat("vertex", np.float32, self.vertex_size),
        )

    def default_candidates(self) -> int:
        """Candidates N verified per query: the ``candidates`` parameter."""
        return int(self.params.candidates)

    def retrieve(
        self, db: GOSMatchDB, query: int, n_allowed: int, k: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` frames of ``[0, n_allowed)`` with the nearest graph descriptors."""
        return db.knn.query(db.graph[query], n_allowed, k)

    def retrieval_pairwise(self, db: GOSMatchDB, rows: np.ndarray, cols) -> np.ndarray:
        """Graph-descriptor L2 distances of frames ``rows`` against ``cols``."""
        return l2_block(db.graph[rows], db.graph[cols])

    # ------------------------------------------------------------------ stage 2

    def rng(self, query: int, candidate: int) -> np.random.Generator:
        """NumPy generator of the reference path for one pair (same pair, same samples)."""
        return np.random.default_rng([int(self.params.seed), int(query), int(candidate)])

    def verify(self, db: GOSMatchDB, query: int, candidates: np.ndarray) -> Verification:
        """Score, pose (candidate -> query LiDAR frame) and inlier count of each candidate."""
        candidates = np.asarray(candidates, dtype=np.int64).reshape(-1)
        p = self.params
        score, pose, inliers = verify_query(
            int(query), candidates, db.offsets, db.centroids, db.classes, db.vertex,
            int(p.ransac_iterations), float(p.inlier_threshold), int(p.min_inliers),
            SCORE_CODES[p.score], int(p.seed),
        )
        return Verification(score=score, pose=pose, inliers=inliers)

    def verify_reference(self, db: GOSMatchDB, query: int, candidates: np.ndarray) -> Verification:
        """:meth:`verify` step by step in NumPy around ``geometry.ransac_rigid``.

        Same correspondences, hypothesis ranking, refit and score; the minimal
        samples come from NumPy's generator seeded by ``(seed, query,
        candidate)`` instead of the kernel's SplitMix64, so a pair can settle on
        a different (equally valid) hypothesis. Slow; for tests and checks.
        """
        candidates = np.asarray(candidates, dtype=np.int64).reshape(-1)
        k = len(candidates)
        score = np.full(k, np.inf)
        pose = np.full((k, 4, 4), np.nan)
        inliers = np.zeros(k, dtype=np.int64)
        q = db.frame(query)
        for a, c in enumerate(candidates):
            res = verify_pair(*q, *db.frame(int(c)), self.verify_settings, self.rng(query, c))
            score[a], inliers[a] = res.score, res.inliers
            if np.isfinite(res.score):
                pose[a] = res.pose
        return Verification(score=score, pose=pose, inliers=inliers)

    def distance(self, query: dict, candidate: dict) -> tuple[float, float]:
        """Verification score of two feature sets and the yaw of the fitted pose."""
        res = verify_pair(
            query["centroids"], query["classes"], query["vertex"],
            candidate["centroids"], candidate["classes"], candidate["vertex"],
            self.verify_settings, np.random.default_rng([int(self.params.seed)]),
        )
        yaw = float(yaw_deg_of(res.pose)) % 360.0 if np.isfinite(res.score) else float("nan")
        return res.score, yaw

    def describe_many(self, scans) -> list[dict[str, np.ndarray]]:  # type: ignore[override]
        """Feature sets of an iterable of scans (a list: they differ in size)."""
        return [self.compute(scan) for scan in scans]
