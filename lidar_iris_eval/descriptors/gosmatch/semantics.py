"""Objects from per-point SemanticKITTI labels: the GOSMatch front end.

The authors ran RangeNet++ and then Euclidean clustering; here the labels are
given (SemanticKITTI ``.label`` files, real or simulated) and only the
clustering is done. Per object class:

1. keep the points whose semantic id (``label & 0xFFFF``) is in the class:
   vehicle = {10 car, 13 bus, 16 on-rails, 18 truck, 20 other-vehicle}
   (the moving ids 252-259 are separate ids and so never enter), trunk = {71},
   pole = {80} plus 81 traffic-sign when ``traffic_signs`` is set;
2. Euclidean clustering: two points closer than ``tolerance`` belong to the
   same cluster (connected components of the radius graph, as PCL's
   ``EuclideanClusterExtraction``); clusters of fewer than ``min_points``
   points are dropped;
3. the centroid (mean point) of each cluster is a vertex when its 3-D range
   is below ``max_range`` (50 m, as the authors' released objects).

Within a class the clusters are ordered largest first (PCL's order), ties by
range; the order only matters to the ``reference`` vertex offset quirk.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np
from scipy.spatial import cKDTree

VEHICLE_IDS: tuple[int, ...] = (10, 13, 16, 18, 20)
TRUNK_IDS: tuple[int, ...] = (71,)
POLE_IDS: tuple[int, ...] = (80,)
TRAFFIC_SIGN_ID = 81


@dataclass(frozen=True)
class ClusterSettings:
    """How labelled points become objects (see the module docstring)."""

    tolerance: float = 0.5
    min_points: int = 10
    max_range: float = 50.0
    traffic_signs: bool = False


def class_ids(settings: ClusterSettings) -> tuple[tuple[int, ...], ...]:
    """The SemanticKITTI ids of each object class (vehicle, trunk, pole)."""
    poles = POLE_IDS + ((TRAFFIC_SIGN_ID,) if settings.traffic_signs else ())
    return VEHICLE_IDS, TRUNK_IDS, poles


def euclidean_clusters(points: np.ndarray, tolerance: float, min_points: int) -> list[np.ndarray]:
    """Index arrays of the clusters of ``points`` (single linkage at ``tolerance``).

    Largest cluster first; clusters below ``min_points`` are dropped.
    """
    n = len(points)
    if n == 0:
        return []
    tree = cKDTree(points)
    pairs = tree.query_pairs(tolerance, output_type="ndarray")
    comp = _components(n, np.ascontiguousarray(pairs, dtype=np.int64))
    n_comp = int(comp.max()) + 1
    sizes = np.bincount(comp, minlength=n_comp)
    keep = np.flatnonzero(sizes >= max(int(min_points), 1))
    order = np.argsort(comp, kind="stable")
    starts = np.concatenate([[0], np.cumsum(sizes)])
    return [order[starts[c]:starts[c + 1]] for c in keep]


@nb.njit(cache=True, nogil=True)
def _components(n: int, pairs: np.ndarray) -> np.ndarray:
    """Connected components of the graph of edges ``pairs``, numbered as SciPy's
    ``connected_components`` numbers them (in order of each component's smallest node).

    Union-find; replaces building a sparse matrix per class, whose conversions
    took much of the clustering's time (scripts/bench_gosmatch_front.py)."""
    parent = np.arange(n)
    for k in range(len(pairs)):
        a, b = pairs[k, 0], pairs[k, 1]
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        while parent[b] != b:
            parent[b] = parent[parent[b]]
            b = parent[b]
        if a != b:
            if a < b:
                parent[b] = a
            else:
                parent[a] = b
    label = np.full(n, -1, dtype=np.int64)
    comp = np.empty(n, dtype=np.int64)
    count = 0
    for i in range(n):
        r = i
        while parent[r] != r:
            r = parent[r]
        if label[r] < 0:
            label[r] = count
            count += 1
        comp[i] = label[r]
    return comp


def objects_from_labels(
    points: np.ndarray, labels: np.ndarray, settings: ClusterSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Object centroids ``(K, 3)`` float64 and class codes ``(K,)`` int8, sorted by class."""
    points = np.asarray(points, dtype=np.float64)[:, :3]
    semantic = np.asarray(labels, dtype=np.uint32) & np.uint32(0xFFFF)
    if len(semantic) != len(points):
        raise ValueError(f"{len(semantic)} labels for {len(points)} points")
    all_centroids, all_classes = [], []
    for code, ids in enumerate(class_ids(settings)):
        member = np.isin(semantic, np.asarray(ids, dtype=np.uint32))
        pts = points[member]
        found = []
        for idx in euclidean_clusters(pts, settings.tolerance, settings.min_points):
            centroid = pts[idx].mean(axis=0)
            rng = float(np.linalg.norm(centroid))
            if rng < settings.max_range:
                found.append((-len(idx), rng, centroid))
        found.sort(key=lambda item: (item[0], item[1]))
        all_centroids.extend(item[2] for item in found)
        all_classes.extend([code] * len(found))
    centroids = np.array(all_centroids, dtype=np.float64).reshape(-1, 3)
    return centroids, np.array(all_classes, dtype=np.int8)
