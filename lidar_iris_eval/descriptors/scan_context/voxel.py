"""Sort-free PCL ``VoxelGrid`` centroids in one compiled pass (numba).

The NumPy route (:func:`..descriptor.voxel_downsample_numpy`) builds one integer
key per point, sorts the 120k keys of a KITTI scan and reduces runs of equal
keys: the sort costs about 70 % of Scan Context's extraction. Here each point
goes straight into an open-addressing hash table keyed by its voxel, which
accumulates float64 sums and counts; only the few thousand occupied voxels
are sorted at the end, so the output order (x index, then y, then z) is the
same as the NumPy route's.

Exactness: both routes compute the voxel index as ``floor(float32(x) *
float32(1 / leaf))`` and the centroid as ``float32(float64 sum / count)``.
They add the points of a voxel in different orders, which cannot change the
sum as long as float64 adds the float32 coordinates without rounding: true
whenever the coordinates of one voxel differ in magnitude by less than
2**28 (a voxel spanning 1e-9 m and 0.4 m would be the exception). On real
KITTI scans and on the tests' random clouds the centroids are bitwise equal.
"""

from __future__ import annotations

import numba
import numpy as np

_EMPTY = -1
#: cell indices beyond this (absurd outliers) are left to the NumPy route
_LIMIT = 2.0**52
#: initial hash-table slots (half of them usable): fits a KITTI scan's ~9k voxels
_CAPACITY = 1 << 15


@numba.njit(cache=True, nogil=True)
def _slot(cx, cy, cz, mask):  # pragma: no cover - compiled
    # murmur3's 64-bit finaliser over a linear mix of the three indices
    h = cx * np.int64(73856093) + cy * np.int64(19349663) + cz * np.int64(83492791)
    h ^= (h >> 33) & np.int64(0x7FFFFFFF)
    h *= np.int64(-49064778989728563)
    h ^= (h >> 33) & np.int64(0x7FFFFFFF)
    return h & mask


@numba.njit(cache=True, nogil=True)
def _voxel_kernel(xyz, inv, reach2, capacity):  # pragma: no cover - compiled
    """Cells ``(V, 3)``, float64 sums ``(V, 3)``, counts ``(V,)`` of the occupied voxels.

    One pass over the points with a fixed table of ``capacity`` slots (a
    power of two); a KITTI scan fills about 9k voxels, so the default table
    stays in cache. Returns a status as well: 0 done, 1 table more than half
    full (call again with a larger one), 2 cell indices beyond 2**52.
    Consecutive points of a scan often share a voxel (83 % on KITTI), so the
    last voxel is checked before hashing.
    """
    mask = capacity - 1
    limit = capacity // 2
    table = np.full(capacity, _EMPTY, dtype=np.int64)
    cells = np.empty((limit, 3), dtype=np.int64)
    sums = np.zeros((limit, 3))
    counts = np.zeros(limit, dtype=np.int64)
    n_vox = 0
    last = -1
    for i in range(xyz.shape[0]):
        x = np.float64(xyz[i, 0])
        y = np.float64(xyz[i, 1])
        if reach2 >= 0.0 and x * x + y * y > reach2:
            continue
        fx = np.floor(xyz[i, 0] * inv)
        fy = np.floor(xyz[i, 1] * inv)
        fz = np.floor(xyz[i, 2] * inv)
        if not (abs(fx) < _LIMIT and abs(fy) < _LIMIT and abs(fz) < _LIMIT):
            return cells[:0], sums[:0], counts[:0], 2
        cx = np.int64(fx)
        cy = np.int64(fy)
        cz = np.int64(fz)
        if last >= 0 and cells[last, 0] == cx and cells[last, 1] == cy and cells[last, 2] == cz:
            v = last
        else:
            slot = _slot(cx, cy, cz, mask)
            while True:
                v = table[slot]
                if v == _EMPTY:
                    if n_vox == limit:
                        return cells[:0], sums[:0], counts[:0], 1
                    v = n_vox
                    table[slot] = v
                    cells[v, 0] = cx
                    cells[v, 1] = cy
                    cells[v, 2] = cz
                    n_vox += 1
                    break
                if cells[v, 0] == cx and cells[v, 1] == cy and cells[v, 2] == cz:
                    break
                slot = (slot + 1) & mask
            last = v
        sums[v, 0] += x
        sums[v, 1] += y
        sums[v, 2] += np.float64(xyz[i, 2])
        counts[v] += 1
    return cells[:n_vox], sums[:n_vox], counts[:n_vox], 0


def voxel_centroids(points: np.ndarray, leaf: float, reach: float | None = None):
    """Voxel-grid centroids of the points within ``reach`` (x-y) of the origin.

    Parameters
    ----------
    points : (N, 3) float32, finite
    leaf : float
        Voxel edge in metres.
    reach : float, optional
        Points farther than this in the x-y plane are skipped (``None``: keep all).

    Returns
    -------
    (V, 3) float32 centroids ordered by voxel (x index, then y, then z), or
    ``None`` for a cloud with cell indices beyond 2**52 (absurd outliers; the
    caller then uses the NumPy route, which ranks the occupied cells).
    """
    xyz = np.ascontiguousarray(points[:, :3], dtype=np.float32)
    reach2 = -1.0 if reach is None else float(reach) * float(reach)
    inv = np.float32(1.0 / leaf)
    capacity = _CAPACITY
    while True:
        cells, sums, counts, status = _voxel_kernel(xyz, inv, reach2, capacity)
        if status == 2:
            return None
        if status == 0:
            break
        capacity *= 4
    order = _lexicographic_order(cells)
    out = np.empty((len(counts), 3), dtype=np.float32)
    out[:] = sums[order] / counts[order, None]
    return out


def _lexicographic_order(cells: np.ndarray) -> np.ndarray:
    """Order of ``(V, 3)`` cells by x, then y, then z (one int64 key when it fits)."""
    if len(cells) == 0:
        return np.empty(0, dtype=np.intp)
    lo = cells.min(axis=0)
    span = cells.max(axis=0) - lo + 1
    if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**62:
        rel = cells - lo
        return np.argsort((rel[:, 0] * span[1] + rel[:, 1]) * span[2] + rel[:, 2])
    return np.lexsort((cells[:, 2], cells[:, 1], cells[:, 0]))
