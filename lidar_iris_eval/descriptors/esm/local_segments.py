"""Segments of one local map (SegMap's segmenter on its accumulated voxel map).

The local map (:mod:`lidar_iris_eval.localmaps`) is already a 0.1 m voxel grid
of filtered scans in the world frame; its voxel centroids are grown into
Euclidean clusters at ``radius`` (0.2 m), clusters of ``min_points`` to
``max_points`` voxels (100-15,000) are segments, each resampled to the
network's 256 points and normalised exactly as single-scan segments are
(:func:`~lidar_iris_eval.descriptors.esm.segmentation.normalise`).

The partition is computed from the whole map at every frame, so the map of
frame ``i`` gives the same segments whatever frame extraction started from.
Persistent segment ids and the embedding cache (which segments need the
network) are :mod:`.tracking`'s; :func:`local_map_clusters` and
:func:`sample_segment` are the pieces it uses (:func:`segment_local_map`, the
untracked function, keeps its index-seeded resampling and its return).
"""

from __future__ import annotations

import hashlib

import numpy as np

from lidar_iris_eval.descriptors.esm.segmentation import (
    SegmentParams,
    euclidean_clusters,
    normalise,
    resample,
)


def local_map_clusters(world_points: np.ndarray, params: SegmentParams) -> list[np.ndarray]:
    """The segments of a local map as arrays of voxel indices (rows of ``world_points``).

    Clusters of ``min_points`` to ``max_points`` voxels, ordered by their first
    voxel (key order, the order of :func:`segment_local_map`); each array is
    increasing.
    """
    pts = np.asarray(world_points, dtype=np.float64)
    if len(pts) == 0:
        return []
    comp = euclidean_clusters(pts, params.radius)
    counts = np.bincount(comp)
    good = np.nonzero((counts >= params.min_points) & (counts <= params.max_points))[0]
    order = np.argsort(comp, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(counts)])
    return [order[bounds[c]:bounds[c + 1]] for c in good]


def content_seed(keys: np.ndarray) -> int:
    """A 64-bit seed from a segment's voxel keys (its content, not its index in the frame)."""
    digest = hashlib.blake2b(np.ascontiguousarray(keys, dtype="<i8").tobytes(), digest_size=8)
    return int.from_bytes(digest.digest(), "little")


def sample_segment(points: np.ndarray, keys: np.ndarray, params: SegmentParams) -> np.ndarray:
    """One segment's network input: ``n_points`` resampled with the stream
    ``[seed, content_seed(keys)]``, normalised as single-scan segments are."""
    rng = np.random.default_rng([params.seed, content_seed(keys)])
    normed, _ = normalise(resample(np.asarray(points, dtype=np.float64), params.n_points, rng),
                          params.norm_scale, params.align_yaw)
    return normed


def segment_local_map(world_points: np.ndarray, params: SegmentParams):
    """Segments of a local map's voxel centroids ``(M, 3)`` (world frame).

    Returns ``(points (S, n_points, 3) float32, world centroids (S, 3), sizes (S,))``;
    segments are ordered by their first voxel (key order), segment ``s`` is
    resampled with the stream ``[seed, s]``.
    """
    pts = np.asarray(world_points, dtype=np.float64)
    members = local_map_clusters(pts, params)
    if not members:
        return (np.zeros((0, params.n_points, 3), np.float32), np.zeros((0, 3)),
                np.zeros(0, np.int64))
    out, cents, sizes = [], [], []
    for s, m in enumerate(members):
        seg = pts[m]
        rng = np.random.default_rng([params.seed, s])
        normed, _ = normalise(resample(seg, params.n_points, rng), params.norm_scale,
                              params.align_yaw)
        out.append(normed)
        cents.append(seg.mean(axis=0))
        sizes.append(len(seg))
    return np.stack(out), np.asarray(cents), np.asarray(sizes, dtype=np.int64)
