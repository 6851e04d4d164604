"""The incremental voxel grid of a local map (SegMap's ``local_map.hpp`` with a scan window).

:class:`VoxelWindow` keeps, per occupied voxel, the number of points and the
integer sum of their coordinates in millimetres, so a voxel's centroid is
exact and does not depend on the order scans were added or dropped: the map
of frame ``i`` is the same whether it was built from frame 0 or from frame
``i - W + 1`` (chunked extraction relies on it). Per frame:

1. **add** scan ``i`` (already filtered, in the world frame);
2. **drop** scan ``i - W`` (its points leave the voxels it fed; a voxel with
   no point left is removed);
3. **crop**: every voxel whose centre is farther than ``radius`` (horizontal)
   from pose ``i`` is removed for good, from the map and from the stored scans
   (SegMap drops far voxels the same way), so memory is bounded by the
   cylinder, not the sequence. (A stored scan marks its cropped voxels dead and
   compacts once a quarter of them are, or when it is dropped: a dead entry is never
   subtracted, so the map is the same as with an immediate removal.)
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numba
import numpy as np

_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def encode(ijk: np.ndarray) -> np.ndarray:
    """One int64 key per integer voxel index ``(n, 3)`` (each within +-2^20)."""
    v = np.asarray(ijk, dtype=np.int64) + _OFFSET
    if len(v) and (v.min() < 0 or v.max() > _MASK):
        raise ValueError("voxel index out of range (more than 2^20 voxels from the origin)")
    return (v[:, 0] << (2 * _BITS)) | (v[:, 1] << _BITS) | v[:, 2]


def decode(keys: np.ndarray) -> np.ndarray:
    """Integer voxel indices ``(n, 3)`` of keys made by :func:`encode`."""
    k = np.asarray(keys, dtype=np.int64)
    return np.stack([(k >> (2 * _BITS)) & _MASK, (k >> _BITS) & _MASK, k & _MASK], 1) - _OFFSET


@dataclass
class _Contribution:
    frame: int
    keys: np.ndarray  # (m,) sorted unique
    #: (m,) int64 columns: points per voxel, then the x, y, z sums in millimetres (1-D
    #: arrays: NumPy's boolean indexing and insertion are several times faster on them
    #: than on the rows of an (m, k) array)
    cols: list
    #: True where a crop removed the voxel and the arrays were not compacted yet; a dead
    #: entry is no contribution (its points left the map with the voxel)
    dead: np.ndarray | None = None
    n_dead: int = 0

    @property
    def counts(self) -> np.ndarray:
        return self.cols[0]

    @property
    def sums(self) -> np.ndarray:
        return np.stack(self.cols[1:], 1)

    def kill(self, pos: np.ndarray) -> None:
        """Mark the entries ``pos`` dead; compact once a quarter of the entries are."""
        if self.dead is None:
            self.dead = np.zeros(len(self.keys), bool)
        pos = pos[~self.dead[pos]]
        self.dead[pos] = True
        self.n_dead += len(pos)
        if 4 * self.n_dead >= len(self.keys):
            self.compact()

    def compact(self) -> None:
        """Remove the dead entries (the arrays then hold exactly the live contribution)."""
        if self.n_dead:
            keep = ~self.dead
            self.keys, self.cols = self.keys[keep], [c[keep] for c in self.cols]
        self.dead, self.n_dead = None, 0


@dataclass(frozen=True)
class LocalMapFrame:
    """The local map of one frame.

    Attributes
    ----------
    frame : the frame ``i``.
    pose : ``(4, 4)`` world-from-LiDAR pose of frame ``i`` (of the odometry used).
    points : ``(M, 3)`` float64 voxel centroids in the world frame, by voxel key.
    counts : ``(M,)`` points per voxel.
    last_seen : ``(M,)`` the latest frame whose scan fed each voxel.
    frames : the frames whose scans the map holds, oldest first.
    keys : ``(M,)`` int64 voxel keys (:func:`encode` of the integer voxel index), sorted;
        the identity of a voxel across frames (segment tracking uses it); ``None``
        when not given.
    """

    frame: int
    pose: np.ndarray
    points: np.ndarray
    counts: np.ndarray
    last_seen: np.ndarray
    frames: tuple[int, ...]
    keys: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.points)

    def local_points(self) -> np.ndarray:
        """The voxel centroids in frame ``i``'s LiDAR frame."""
        inv = np.linalg.inv(self.pose)
        return self.points @ inv[:3, :3].T + inv[:3, 3]


class VoxelWindow:
    """A voxel grid of the last ``window`` scans, cropped to a cylinder (module docstring)."""

    def __init__(self, window: int, voxel: float = 0.1, radius: float = 50.0):
        if window < 1:
            raise ValueError("window must be at least 1")
        self.window, self.radius = int(window), float(radius)
        self.voxel_mm = int(round(voxel * 1000))
        if self.voxel_mm < 1:
            raise ValueError("voxel must be at least 1 mm")
        self.keys = np.zeros(0, np.int64)
        # per voxel, five 1-D int64 columns: count, the x, y, z sums (mm), last frame
        # (1-D: a removal or an insertion is a fast copy per column; see _Contribution)
        self.cols = [np.zeros(0, np.int64) for _ in range(5)]
        self.scans: deque[_Contribution] = deque()
        self._zeros = False  # voxels with no point left wait for the next crop

    @property
    def counts(self) -> np.ndarray:
        """``(M,)`` points per voxel."""
        return self.cols[0]

    @property
    def sums(self) -> np.ndarray:
        """``(M, 3)`` integer sums of the voxels' coordinates in millimetres (a copy)."""
        return np.stack(self.cols[1:4], 1)

    @property
    def last(self) -> np.ndarray:
        """``(M,)`` the latest frame whose scan fed each voxel."""
        return self.cols[4]

    def __len__(self) -> int:
        return len(self.keys)

    # ------------------------------------------------------------------ updates

    def add(self, frame: int, world_points: np.ndarray) -> None:
        """Feed the scan of ``frame`` (``(n, 3)`` world-frame points)."""
        if self.scans and frame <= self.scans[-1].frame:
            raise ValueError(f"frames must increase: {frame} after {self.scans[-1].frame}")
        mm = np.rint(np.asarray(world_points, dtype=np.float64)[:, :3] * 1000.0).astype(np.int64)
        keys = encode(np.floor_divide(mm, self.voxel_mm))
        # one stable sort groups the points by voxel (the order of np.unique and of its
        # inverse); the integer sums do not depend on the order within a voxel anyway
        order = np.argsort(keys, kind="stable")
        sorted_keys = keys[order]
        starts = np.flatnonzero(np.concatenate([[True], sorted_keys[1:] != sorted_keys[:-1]]))
        starts = starts[: len(sorted_keys)]  # no group in an empty scan
        uniq = sorted_keys[starts]
        bounds = np.concatenate([starts, [len(sorted_keys)]])
        cols = [np.diff(bounds).astype(np.int64)]
        csum = np.zeros(len(keys) + 1, np.int64)
        for axis in range(3):
            np.cumsum(mm[order, axis], out=csum[1:])
            cols.append(csum[bounds[1:]] - csum[bounds[:-1]])
        self.scans.append(_Contribution(int(frame), uniq, cols))
        pos = np.searchsorted(self.keys, uniq)
        present = pos < len(self.keys)
        present[present] = self.keys[pos[present]] == uniq[present]
        hit = pos[present]
        for mine, theirs in zip(self.cols[:4], cols, strict=True):
            mine[hit] += theirs[present]
        self.cols[4][hit] = frame
        new = ~present
        if new.any():  # merge the new voxels in place of sorting the whole map again
            at = pos[new]
            self.keys = np.insert(self.keys, at, uniq[new])
            self.cols = [np.insert(mine, at, theirs[new])
                         for mine, theirs in zip(self.cols[:4], cols, strict=True)] + [
                np.insert(self.cols[4], at, np.int64(frame))]

    def drop_before(self, frame: int, compact: bool = True) -> None:
        """Drop every stored scan of a frame ``<= frame - window`` (the window rule).

        ``compact=False`` leaves the voxels with no point left in the arrays until the
        next :meth:`crop` removes them with the far ones (one copy per frame, not two);
        the map is only read after that crop.
        """
        while self.scans and self.scans[0].frame <= frame - self.window:
            c = self.scans.popleft()
            c.compact()
            pos = np.searchsorted(self.keys, c.keys)  # every live key is present (invariant)
            for mine, theirs in zip(self.cols[:4], c.cols, strict=True):
                mine[pos] -= theirs
            self._zeros = True
        if compact and self._zeros:
            self._keep(self.counts > 0)

    def crop(self, centre_xy: np.ndarray) -> None:
        """Remove for good every voxel whose centre is farther than ``radius`` away."""
        inside = self._inside(self.keys, centre_xy)
        if self._zeros:
            live = self.counts > 0
            keep = inside & live
            gone = self.keys[~inside & live]
        else:
            keep, gone = inside, self.keys[~inside]
        if len(keep) and keep.all():
            self._zeros = False
            return
        self._keep(keep)
        if not len(gone):
            return
        for c in self.scans:  # look the few leaving voxels up, not every stored voxel
            pos = np.searchsorted(c.keys, gone)
            found = pos < len(c.keys)
            pos = pos[found]
            pos = pos[c.keys[pos] == gone[found]]
            if len(pos):
                c.kill(pos)

    # ------------------------------------------------------------------ reading

    def centroids(self) -> np.ndarray:
        """``(M, 3)`` voxel centroids in metres (world frame), in key order."""
        out = np.empty((len(self.keys), 3))
        for axis in range(3):  # sum / count / 1000, the same float64 operations per element
            out[:, axis] = self.cols[1 + axis] / self.cols[0] / 1000.0
        return out

    def frames(self) -> tuple[int, ...]:
        return tuple(c.frame for c in self.scans)

    def stored_voxels(self) -> int:
        """Voxels held by the stored scans (the memory besides the map itself); compacts them."""
        for c in self.scans:
            c.compact()
        return int(sum(len(c.keys) for c in self.scans))

    # ------------------------------------------------------------------ helpers

    def _inside(self, keys: np.ndarray, centre_xy: np.ndarray) -> np.ndarray:
        c = np.asarray(centre_xy, dtype=np.float64)
        return _inside_xy(np.ascontiguousarray(keys, dtype=np.int64), self.voxel_mm / 1000.0,
                          float(c[0]), float(c[1]), float(self.radius**2))

    def _keep(self, mask: np.ndarray) -> None:
        self.keys, self.cols = self.keys[mask], [c[mask] for c in self.cols]
        self._zeros = False


@numba.njit(cache=True)
def _inside_xy(keys: np.ndarray, v: float, cx: float, cy: float,
               r2: float) -> np.ndarray:  # pragma: no cover - compiled
    """Voxel centres (horizontal indices of the keys) within ``sqrt(r2)`` of (cx, cy),
    with the float64 operations of NumPy's expression, in one pass."""
    out = np.empty(len(keys), np.bool_)
    for t in range(len(keys)):
        k = keys[t]
        dx = (((k >> (2 * _BITS)) & _MASK) - _OFFSET + 0.5) * v - cx
        dy = (((k >> _BITS) & _MASK) - _OFFSET + 0.5) * v - cy
        out[t] = dx * dx + dy * dy <= r2
    return out


class LocalMap:
    """Frame-by-frame local maps: filter, place, add, drop, crop (module docstring)."""

    def __init__(self, window: int, voxel: float = 0.1, radius: float = 50.0,
                 input_filter=None):
        from lidar_iris_eval.localmaps.filters import INPUT_FILTERS

        self.grid = VoxelWindow(window, voxel, radius)
        self.filter = input_filter if input_filter is not None else INPUT_FILTERS["segmap"]

    def update(self, frame: int, points: np.ndarray, pose: np.ndarray) -> None:
        """Add the scan of ``frame`` (sensor-frame points, world-from-LiDAR ``pose``)."""
        pose = np.asarray(pose, dtype=np.float64)
        kept = self.filter.apply(points)
        self.grid.add(frame, kept @ pose[:3, :3].T + pose[:3, 3])
        self.grid.drop_before(frame, compact=False)
        self.grid.crop(pose[:2, 3])

    def frame(self, frame: int, pose: np.ndarray) -> LocalMapFrame:
        """The current map as a :class:`LocalMapFrame` of ``frame``."""
        g = self.grid
        return LocalMapFrame(int(frame), np.asarray(pose, dtype=np.float64), g.centroids(),
                             g.counts.copy(), g.last.copy(), g.frames(), g.keys.copy())
