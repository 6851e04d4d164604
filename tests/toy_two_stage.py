"""A toy two-stage method for the pipeline tests: labelled objects, retrieval, Kabsch.

Not a published method; it exists to push the whole two-stage path (labels in,
variable-size features, cache, retrieval, verification with a 6-DoF pose)
through the pipeline on simulated data, using the shared geometric tools.

* ``compute(scan)`` needs labels: the centroids of parked-car instances (class
  10, instance id in the high 16 bits) with at least ``min_points`` points, a
  0.5 m voxel subsample of the static structure (cars, buildings, trunks,
  poles) and a rotation-invariant histogram of centroid pair distances.
* ``retrieve``: the ``k`` nearest histograms (L1) among the allowed frames.
* ``verify``: objects are paired by mutual nearest neighbours of a
  rotation-invariant signature (sorted distances to their nearest objects),
  RANSAC + Kabsch on the paired centroids gives an initial pose, point-to-point
  ICP (nearest neighbours + Kabsch) on the static points refines it; the score
  is 1 - the fraction of points within 0.3 m after alignment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor, Verification
from lidar_iris_eval.matching.geometry import (
    kabsch,
    mutual_nearest,
    nearest_neighbours,
    ransac_rigid,
    transform_points,
)

STATIC_CLASSES = (10, 50, 71, 80)


@dataclass(frozen=True)
class ToyObjectsParams:
    object_class: int = 10
    min_points: int = 15
    voxel: float = 0.5
    max_range: float = 40.0
    signature: int = 4
    num_candidates: int = 5
    delay: float = 0.0  # seconds per scan, so a test can kill an extraction mid-run


class ToyObjects(Descriptor):
    name = "toy-objects"
    params_type = ToyObjectsParams
    inputs = frozenset({"points", "labels"})
    two_stage = True

    def compute(self, scan) -> dict[str, np.ndarray]:
        p = self.params
        if p.delay:
            import time

            time.sleep(p.delay)
        pts = scan.points.astype(np.float64)
        sem = scan.labels & 0xFFFF
        inst = scan.labels >> 16
        near = np.hypot(pts[:, 0], pts[:, 1]) < p.max_range
        cars = (sem == p.object_class) & near
        ids, counts = np.unique(inst[cars], return_counts=True)
        ids = ids[counts >= p.min_points]
        cents = np.array([pts[cars & (inst == i)].mean(axis=0) for i in ids]).reshape(-1, 3)
        static = np.isin(sem, STATIC_CLASSES) & near
        vox = np.floor(pts[static] / p.voxel).astype(np.int64)
        _, first = np.unique(vox, axis=0, return_index=True)
        sample = pts[static][np.sort(first)].astype(np.float32)
        d = np.linalg.norm(cents[:, None] - cents[None], axis=2)
        hist, _ = np.histogram(
            d[np.triu_indices(len(cents), 1)], bins=20, range=(0, 2 * p.max_range)
        )
        hist = hist / max(1, hist.sum())
        return {"centroids": cents, "points": sample, "hist": hist.astype(np.float64)}

    def prepare(self, features):
        return {"features": features, "hist": features.stacked("hist")}

    def retrieve(self, db, query, n_allowed, k):
        d = np.abs(db["hist"][:n_allowed] - db["hist"][query]).sum(axis=1)
        order = np.argsort(d, kind="stable")[:k]
        return order.astype(np.int64), d[order]

    def _signature(self, cents: np.ndarray) -> np.ndarray:
        m = self.params.signature
        if len(cents) <= m:
            return np.zeros((len(cents), m))
        dist, _ = nearest_neighbours(cents, cents, k=m + 1)
        return dist[:, 1:]

    def verify(self, db, query, candidates) -> Verification:
        feats = db["features"]
        q = feats[query]
        k = len(candidates)
        score = np.full(k, np.inf)
        pose = np.full((k, 4, 4), np.nan)
        inliers = np.zeros(k, np.int64)
        for n, c in enumerate(np.asarray(candidates)):
            cand = feats[int(c)]
            ia, ib, _ = mutual_nearest(self._signature(q["centroids"]),
                                       self._signature(cand["centroids"]))
            if len(ia) < 3:
                continue
            rng = np.random.default_rng([int(query), int(c)])
            fit = ransac_rigid(cand["centroids"][ib], q["centroids"][ia], threshold=1.5,
                               iterations=100, min_inliers=3, rng=rng)
            if not fit.success:
                continue
            T = self._icp(fit.pose, cand["points"], q["points"])
            moved = transform_points(T, cand["points"])
            dist, _ = nearest_neighbours(moved, q["points"])
            close = dist < 0.3
            score[n] = 1.0 - close.mean()
            pose[n] = T
            inliers[n] = int(close.sum())
        return Verification(score, pose, inliers)

    @staticmethod
    def _icp(T: np.ndarray, src: np.ndarray, dst: np.ndarray, iterations: int = 15) -> np.ndarray:
        for radius in (2.0,) * 5 + (0.8,) * (iterations - 5):
            dist, idx = nearest_neighbours(transform_points(T, src), dst)
            ok = dist < radius
            if ok.sum() < 3:
                break
            T = kabsch(src[ok], dst[idx[ok]])
        return T


@dataclass(frozen=True)
class SlowToyObjectsParams(ToyObjectsParams):
    delay: float = 0.03


class SlowToyObjects(ToyObjects):
    """ToyObjects that sleeps per scan, so a test can kill its extraction mid-run."""

    params_type = SlowToyObjectsParams
    #: first point of every scan computed in this process (a warm-up call repeats one)
    computed: set = set()

    def compute(self, scan):
        SlowToyObjects.computed.add(tuple(scan.points[0].tolist()))
        return super().compute(scan)
