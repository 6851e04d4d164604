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

import numba
import numpy as np

from lidar_iris_eval.descriptors.esm.segmentation import (
    SegmentParams,
    euclidean_clusters,
    grid_clusters,
    normalise,
    resample,
)

#: the steepest ground slope :func:`local_ground_mask` carries from a column to the next (deg)
GROUND_MAX_SLOPE = 15.0
#: :func:`local_ground_mask` holds a dense grid of columns up to this many cells (or 4 per
#: point), else it works on the occupied columns only
DENSE_COLUMNS = 1 << 22


def local_ground_mask(points: np.ndarray, cell: float, clearance: float) -> np.ndarray:
    """True for the voxels of a local map that lie on the local ground.

    The map (world frame, z up) is cut into ``cell`` x ``cell`` m columns; the
    ground height of a column is its lowest voxel, unless one of its 8
    neighbours' lowest voxels plus the rise of a ``GROUND_MAX_SLOPE`` (15 deg)
    slope over the distance between the two columns is lower (a column that
    holds only a car or a wall base takes the ground beside it); a voxel at most
    ``clearance`` m above the ground height of its column is ground. It
    follows slopes and a tilted sensor, which a height rule in the sensor frame
    (SegMap's z >= -1 m) does not.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(0, bool)
    # compiled (one pass per step instead of NumPy's ~20 over 250k voxels, and no
    # ``np.minimum.at``); the same float64 operations, so the same mask
    i, j, rows, width = _columns(pts[:, 0], pts[:, 1], float(cell))
    rise = cell * np.tan(np.radians(GROUND_MAX_SLOPE))
    if rows * width > max(4 * len(pts), DENSE_COLUMNS):  # sparse columns: tiny cells
        return _sparse_ground_mask(pts[:, 2], i * width + j, width, cell, clearance)
    # a dense grid of columns (the map is a bounded cylinder): empty columns stay +inf,
    # and inf + rise is inf, so they never lower a neighbour
    steps = np.array([rise * np.hypot(di, dj) for di, dj in _NEIGHBOURS])
    return _dense_ground_mask(i, j, np.ascontiguousarray(pts[:, 2]), rows, width, steps,
                              float(clearance))


#: the 8 neighbouring columns (row, column offsets) of :func:`local_ground_mask`
_NEIGHBOURS = np.array([(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1)
                        if di != 0 or dj != 0], np.int64)


@numba.njit(cache=True)
def _columns(x: np.ndarray, y: np.ndarray, cell: float) -> tuple:  # pragma: no cover
    """Each point's column ``floor(x / cell)``, ``floor(y / cell)``, shifted to leave
    a free border of one column, and the grid's size (rows, width)."""
    n = len(x)
    i = np.empty(n, np.int64)
    j = np.empty(n, np.int64)
    for t in range(n):
        i[t] = np.int64(np.floor(x[t] / cell))
        j[t] = np.int64(np.floor(y[t] / cell))
    i_min, j_min = i.min(), j.min()
    for t in range(n):
        i[t] -= i_min - 1
        j[t] -= j_min - 1
    return i, j, int(i.max()) + 2, int(j.max()) + 2


@numba.njit(cache=True)
def _nan_min(a: float, b: float) -> float:  # pragma: no cover - compiled
    """``np.minimum`` of two floats (NaN wins)."""
    if np.isnan(a) or np.isnan(b):
        return np.nan
    return a if a <= b else b


@numba.njit(cache=True)
def _dense_ground_mask(i: np.ndarray, j: np.ndarray, z: np.ndarray, rows: int, width: int,
                       steps: np.ndarray, clearance: float) -> np.ndarray:  # pragma: no cover
    """:func:`local_ground_mask` on a dense grid of columns: each column's lowest z,
    lowered by a neighbour's lowest plus its step (``steps`` in ``_NEIGHBOURS``
    order), then z <= ground + clearance."""
    lowest = np.full((rows, width), np.inf)
    for t in range(len(z)):
        lowest[i[t], j[t]] = _nan_min(lowest[i[t], j[t]], z[t])
    ground = lowest.copy()
    for a in range(1, rows - 1):
        for b in range(1, width - 1):
            g = ground[a, b]
            for m in range(8):
                g = _nan_min(g, lowest[a + _NEIGHBOURS[m, 0], b + _NEIGHBOURS[m, 1]]
                             + steps[m])
            ground[a, b] = g
    out = np.empty(len(z), np.bool_)
    for t in range(len(z)):
        out[t] = z[t] <= ground[i[t], j[t]] + clearance
    return out


def local_ground_mask_reference(points: np.ndarray, cell: float,
                                clearance: float) -> np.ndarray:
    """:func:`local_ground_mask` in NumPy (the route before it was compiled; tests)."""
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.zeros(0, bool)
    i = np.floor(pts[:, 0] / cell).astype(np.int64)
    j = np.floor(pts[:, 1] / cell).astype(np.int64)
    i -= i.min() - 1  # a free border for the neighbours
    j -= j.min() - 1
    rows, width = int(i.max()) + 2, int(j.max()) + 2
    flat = i * width + j
    if rows * width > max(4 * len(pts), DENSE_COLUMNS):  # sparse columns: tiny cells
        return _sparse_ground_mask(pts[:, 2], flat, width, cell, clearance)
    lowest = np.full(rows * width, np.inf)
    np.minimum.at(lowest, flat, pts[:, 2])
    lowest = lowest.reshape(rows, width)
    ground = lowest.copy()
    rise = cell * np.tan(np.radians(GROUND_MAX_SLOPE))
    inner = ground[1:-1, 1:-1]
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            step = rise * np.hypot(di, dj)
            np.minimum(inner, lowest[1 + di:rows - 1 + di, 1 + dj:width - 1 + dj] + step,
                       out=inner)
    return pts[:, 2] <= ground.reshape(-1)[flat] + clearance


def _sparse_ground_mask(z: np.ndarray, flat: np.ndarray, width: int, cell: float,
                        clearance: float) -> np.ndarray:
    """:func:`local_ground_mask` over the occupied columns only (``flat``: each point's
    column on a grid ``width`` wide with a free border), for grids too large to hold."""
    cells, inverse = np.unique(flat, return_inverse=True)
    lowest = np.full(len(cells), np.inf)
    np.minimum.at(lowest, inverse, z)
    ground = lowest.copy()
    rise = cell * np.tan(np.radians(GROUND_MAX_SLOPE))
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            if di == 0 and dj == 0:
                continue
            other = cells + di * width + dj
            pos = np.minimum(np.searchsorted(cells, other), len(cells) - 1)
            hit = cells[pos] == other
            ground[hit] = np.minimum(ground[hit], lowest[pos[hit]] + rise * np.hypot(di, dj))
    return z <= ground[inverse] + clearance


def local_map_clusters(world_points: np.ndarray, params: SegmentParams) -> list[np.ndarray]:
    """The segments of a local map as arrays of voxel indices (rows of ``world_points``).

    Clusters of ``min_points`` to ``max_points`` voxels, ordered by their first
    voxel (key order, the order of :func:`segment_local_map`); each array is
    increasing. The front end's two optional steps (``SegmentParams``):

    * ``ground_cell > 0``: the voxels of :func:`local_ground_mask` are removed first;
    * ``cluster_voxel > 0`` (**density normalisation**): the remaining voxels
      are grouped into voxels of ``cluster_voxel`` m, whose centroids are grown
      at ``radius`` and whose count is what ``min_points`` / ``max_points``
      bound, so a segment's size is its occupied volume at one resolution,
      whatever the sensor's density; a segment holds every map voxel of its
      coarse voxels.
    """
    pts = np.asarray(world_points, dtype=np.float64)
    if len(pts) == 0:
        return []
    rows = np.arange(len(pts))
    if params.ground_cell > 0:
        rows = rows[~local_ground_mask(pts, params.ground_cell, params.ground_clearance)]
        if len(rows) == 0:
            return []
    kept = pts[rows]
    if params.cluster_voxel > 0:
        i, j, k = (np.floor(kept[:, a] / params.cluster_voxel).astype(np.int64)
                   for a in range(3))
        origin = np.array([i.min(), j.min(), k.min()])
        i, j, k = i - origin[0], j - origin[1], k - origin[2]
        # one int64 per coarse voxel, in the lexicographic (i, j, k) order of the rows
        span_j, span_k = int(j.max()) + 1, int(k.max()) + 1
        flat = (i * span_j + j) * span_k + k
        uniq, coarse, n_fine = np.unique(flat, return_inverse=True, return_counts=True)
        # sums accumulated in row order, as np.add.at does
        sums = np.stack([np.bincount(coarse, kept[:, a], len(n_fine)) for a in range(3)], 1)
        # each coarse centroid lies in its coarse voxel: grown on that grid
        cells = np.stack([uniq // (span_j * span_k), (uniq // span_k) % span_j, uniq % span_k],
                         1)
        comp_coarse = grid_clusters(sums / n_fine[:, None], cells, params.cluster_voxel,
                                    params.radius, origin)
        counts = np.bincount(comp_coarse)
        comp = comp_coarse[coarse]
    else:
        comp = euclidean_clusters(kept, params.radius)
        counts = np.bincount(comp)
    good = np.nonzero((counts >= params.min_points) & (counts <= params.max_points))[0]
    order = np.argsort(comp, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(np.bincount(comp, minlength=len(counts)))])
    members = [rows[order[bounds[c]:bounds[c + 1]]] for c in good]
    members.sort(key=lambda m: int(m[0]))
    return members


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
