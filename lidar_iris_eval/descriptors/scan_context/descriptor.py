"""Scan Context (Kim & Kim, IROS 2018), faithful to the authors' C++ implementation.

A scan is voxel-downsampled, lifted by the sensor height and binned into
``rings x sectors`` polar bins (4 m rings, 6 degree sectors out to
80 m by default); each bin keeps the maximum height of its points (0 = empty).
Two descriptors are compared by ``1 - mean cosine`` over the columns
(sectors) non-empty in both, minimised over circular column shifts.

Presets (``lidar_iris_eval/descriptors/scan_context/presets.yaml``)
---------------------------------------------------
``reference`` (default)
    The authors' C++ (``scancontext_tro/cpp/module/Scancontext``) fed with a
    0.5 m PCL ``VoxelGrid``: +2 m height offset, points beyond 80 m dropped,
    ring key = row mean, shift search = sector-key alignment then +-3 columns.
``exhaustive``
    As ``reference`` but every column shift is tried (the MATLAB ``sc_dist.m``
    and python ``Distance_SC.py`` search). ``d_exhaustive <= d_reference``.
``paper``
    The IROS 2018 paper where it differs from the C++: ring key = occupancy
    (non-empty bins per ring / ``sectors``, MATLAB ``sc2invkeyL0.m``), all
    shifts (the sector-key alignment is "not in original IROS18", C++ comment),
    and the sum of column cosines divided by ``sectors`` (eq. 5) rather
    than by the number of columns valid in both. On full 360-degree scans,
    where every column is non-empty, only the ring key differs from
    ``exhaustive``. What the paper leaves open (downsampling, height offset)
    follows the C++.

Agreement with the authors' C++ (KITTI 00 scans 94, 95, 198, 199 and 94
turned 90 and 180 degrees; ALGORITHMS.md): all five published distances are
reproduced to their 4 decimals and all shifts exactly, for both the
sector-key and the all-shift search (tested in ``tests/test_scan_context.py``).

Conventions and differences from the authors' code
--------------------------------------------------
* **Voxel grid.** PCL ``VoxelGrid`` semantics: voxel index
  ``floor(x * float32(1 / leaf))`` per axis, so voxel faces sit at integer
  multiples of the leaf in the sensor frame (PCL subtracts the bounding-box
  minimum index, which renumbers voxels but does not move their faces); each
  voxel becomes the mean of its points. PCL sums in float32 in an unspecified
  order; we sum in float64 and round the mean to float32 (differences of an
  ulp, which only matter for a centroid on a bin edge). Non-finite points are
  dropped, as PCL does (with a warning here).
* **Binning** mirrors the C++ arithmetic, including its float32 steps:
  ``ring = clip(ceil(r / 80 * 20), 1, 20) - 1`` (ring 0 is ``[0, 4]``, ring i
  ``(4i, 4i + 4]``), ``sector = clip(ceil(theta / 360 * 60), 1, 60) - 1`` with
  ``theta`` in ``[0, 360)`` counter-clockwise from +x via the C++ quadrant
  formula (``theta(0, 0)`` is NaN there and lands in sector 0, as here);
  bins start at -1000 and are reset to 0 if untouched, so the value of a
  bin is ``max(float32(z + 2))``.
* **Cosines** are computed from unit columns quantised to ``2**-16``
  (see :mod:`.kernels`) so that single-pair and batched
  distances are bitwise identical; ``d`` differs from the C++ double result by
  at most about 2e-6 (``d(a, a)`` is ~2e-6 rather than 0).
* **Symmetry.** With every shift tried, ``d(a, b) == d(b, a)`` bitwise (the
  integer correlations satisfy ``S_ab(k) == S_ba(-k)``), so the ``exhaustive``
  and ``paper`` instances set ``symmetric = True``; the sector-key window is
  not symmetric by construction (tie-breaking), so ``reference`` does not.
* **Sector-key alignment** (``reference``): the C++ takes the first shift
  minimising ``||v_q - roll(v_c, s)||``; we take the first shift maximising
  the correlation of the unit-normalised, quantised sector keys, which is the
  same shift except for near-ties (relative gaps below ~1e-5).
* **No valid column**: the C++ returns ``(1e7, 0)`` when no shift has a
  column valid in both; we return ``(nan, nan)``.
* **Yaw.** The C++ returns shift ``k``: ``sc_q`` matches ``sc_c`` with column
  ``c`` moved to ``(c + k) % 60`` (``np.roll(sc_c, k, axis=1)``), i.e. the
  candidate is the query turned clockwise by ``6k`` degrees. The base class
  wants the candidate's counter-clockwise angle, so
  ``yaw = (-6 k) mod 360`` and ``k = (-yaw / 6) mod 60`` (see
  :func:`yaw_to_shift`). Example: the query turned 90 degrees CCW gives C++
  shift 45 and yaw 90.
* **MATLAB differences not adopted** (``ptcloud2polarcontext.m``): no height
  offset, far points kept in the last ring, and bins with fewer than 5 points
  set to 0.
* **Retrieval**: :meth:`ScanContext.candidates` returns the ``k`` nearest ring
  keys (scipy ``cKDTree``, exact Euclidean search in float64), as the C++
  nanoflann tree (float32 keys, top 10) and the MATLAB example (top 50,
  "SC-50") do; exclusion windows are the caller's job.
* **Speed.** :meth:`ScanContext.pairwise` evaluates every shift of blocks of
  pairs with FFT-domain BLAS products; :meth:`ScanContext.matcher` prepares a
  database once for callers that match one query at a time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from scipy.spatial import cKDTree

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.scan_context import kernels, pair, voxel
from lidar_iris_eval.errors import LirisError, warn

RING_KEYS = ("mean", "occupancy")
SEARCHES = ("sector-key", "exhaustive")
DIVISORS = ("valid", "sectors")

#: the C++ initial bin value; bins never raised above it become 0
_NO_POINT = -1000.0


@dataclass(frozen=True)
class ScanContextParams:
    """Every Scan Context parameter; defaults are the authors' C++ values.

    Attributes
    ----------
    rings, sectors : int
        Polar grid size (20 rings of 4 m, 60 sectors of 6 degrees); named like
        LiDAR Iris' ``rings``/``sectors`` (``num_rings``/``num_sectors`` until 0.1).
    max_radius : float
        Points farther than this (metres, in the x-y plane) are dropped.
    lidar_height : float
        Added to z so that ground-level maxima are positive and cannot be
        confused with empty bins (0).
    voxel_size : float
        Leaf of the voxel-grid downsampling in metres; 0 disables it.
    ring_key : {"mean", "occupancy"}
        Rotation-invariant key: row mean (C++) or fraction of non-empty bins
        per ring (IROS 2018 paper).
    search : {"sector-key", "exhaustive"}
        Column shifts tried: ``search_radius`` around the sector-key alignment
        (C++), or all of them.
    search_radius : int
        Half-width of the sector-key window in columns; the C++ uses
        ``round(0.5 * 0.1 * sectors) = 3``.
    divide_by : {"valid", "sectors"}
        Mean of the column cosines over the columns valid in both (C++) or
        sum divided by ``sectors`` (paper eq. 5).
    num_candidates : int
        Default ``k`` of :meth:`ScanContext.candidates` (C++ 10, MATLAB 50).
    """

    rings: int = 20
    sectors: int = 60

    #: old spellings, accepted with a deprecation warning for one release
    renamed: ClassVar[dict[str, str]] = {"num_rings": "rings", "num_sectors": "sectors"}
    max_radius: float = 80.0
    lidar_height: float = 2.0
    voxel_size: float = 0.5
    ring_key: str = "mean"
    search: str = "sector-key"
    search_radius: int = 3
    divide_by: str = "valid"
    num_candidates: int = 10

    def __post_init__(self) -> None:
        def bad(key: str, problem: str) -> LirisError:
            return LirisError(f"scan-context {key}", problem)

        for key in ("rings", "sectors", "num_candidates"):
            if getattr(self, key) < 1:
                raise bad(key, "must be at least 1")
        if self.search_radius < 0:
            raise bad("search_radius", "must be >= 0")
        if not (math.isfinite(self.max_radius) and self.max_radius > 0):
            raise bad("max_radius", "must be a positive finite number")
        if not (math.isfinite(self.voxel_size) and self.voxel_size >= 0):
            raise bad("voxel_size", "must be >= 0 (0 disables downsampling)")
        if not math.isfinite(self.lidar_height):
            raise bad("lidar_height", "must be finite")
        for key, choices in (
            ("ring_key", RING_KEYS),
            ("search", SEARCHES),
            ("divide_by", DIVISORS),
        ):
            if getattr(self, key) not in choices:
                raise bad(key, f"must be one of {', '.join(choices)}")


def voxel_downsample(points: np.ndarray, leaf: float) -> np.ndarray:
    """Replace the points of each ``leaf``-sized voxel by their mean (PCL ``VoxelGrid``).

    Runs the compiled hash-table pass of :mod:`.voxel` (no sort of the points);
    :func:`voxel_downsample_numpy` is the sort-based reference it equals bitwise
    (tested), and the fallback for clouds with absurd outliers.

    Parameters
    ----------
    points : (N, 3) float32
    leaf : float
        Voxel edge in metres; faces lie at integer multiples of ``leaf``.

    Returns
    -------
    (V, 3) float32 centroids, ordered by voxel (x index, then y, then z); an
    empty cloud gives ``(0, 3)`` (the reference's answer).
    """
    out = voxel.voxel_centroids(points, leaf) if len(points) else None
    return voxel_downsample_numpy(points, leaf) if out is None else out


def voxel_downsample_numpy(points: np.ndarray, leaf: float) -> np.ndarray:
    """Sort-based NumPy voxel grid: the reference of :func:`voxel_downsample`.

    Same parameters and result as :func:`voxel_downsample`, which it equals
    bitwise.
    """
    if len(points) == 0:
        return np.empty((0, 3), dtype=np.float32)
    cols = np.ascontiguousarray(points.T, dtype=np.float32)
    inv = np.float32(1.0 / leaf)  # PCL keeps the inverse leaf in float32
    key = np.zeros(len(points), dtype=np.int64)
    for axis in range(3):
        cell = np.floor(cols[axis] * inv)
        lo, span = cell.min(), cell.max() - cell.min()
        if span < 2**20:
            index, size = (cell - lo).astype(np.int64), int(span) + 1
        else:  # absurd outliers: rank the occupied cells instead of spanning them
            cells, index = np.unique(cell, return_inverse=True)
            size = len(cells)
        key = key * size + index
    order = np.argsort(key)
    sorted_key = key[order]
    first = np.empty(len(key), dtype=bool)
    first[0] = True
    np.not_equal(sorted_key[1:], sorted_key[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, len(key)))
    out = np.empty((len(starts), 3), dtype=np.float32)
    for axis in range(3):
        out[:, axis] = np.add.reduceat(cols[axis][order].astype(np.float64), starts) / counts
    return out


def polar_angle_deg(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Azimuth in ``[0, 360)`` degrees, CCW from +x, with the C++ ``xy2theta`` arithmetic.

    float32 ratio, double ``atan``, float32 result; ``(0, 0)`` gives NaN.
    """
    x = np.asarray(x, dtype=np.float32)
    y = np.asarray(y, dtype=np.float32)
    deg = 180.0 / np.pi
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(x >= 0, y / x, y / -x).astype(np.float64)
        ratio_q4 = (-y / x).astype(np.float64)
    a = deg * np.arctan(ratio)
    theta = np.where(
        x >= 0,
        np.where(y >= 0, a, 360.0 - deg * np.arctan(ratio_q4)),
        np.where(y >= 0, 180.0 - a, 180.0 + deg * np.arctan(-ratio)),
    )
    return theta.astype(np.float32)


def polar_context(points: np.ndarray, params: ScanContextParams) -> np.ndarray:
    """The ``(rings, sectors)`` float32 max-height image of ``(N, 3)`` points."""
    p = params
    x, y = points[:, 0], points[:, 1]
    height = (points[:, 2].astype(np.float64) + p.lidar_height).astype(np.float32)
    radius = np.sqrt(x * x + y * y)  # float32, as the C++
    keep = radius <= p.max_radius
    radius, height = radius[keep], height[keep]
    theta = polar_angle_deg(x[keep], y[keep]).astype(np.float64)
    ring = np.ceil(radius.astype(np.float64) / p.max_radius * p.rings)
    sector = np.ceil(theta / 360.0 * p.sectors)
    sector[np.isnan(sector)] = 1.0  # C++: int(NaN) is INT_MIN, clamped up to 1
    ring = np.clip(ring, 1, p.rings).astype(np.intp) - 1
    sector = np.clip(sector, 1, p.sectors).astype(np.intp) - 1
    flat = np.full(p.rings * p.sectors, _NO_POINT, dtype=np.float32)
    np.maximum.at(flat, ring * p.sectors + sector, height)
    flat[flat == _NO_POINT] = 0.0
    return flat.reshape(p.rings, p.sectors)


def ring_key(sc: np.ndarray, kind: str) -> np.ndarray:
    """Rotation-invariant ``(..., R)`` key: row mean, or fraction of non-empty bins."""
    sc = np.asarray(sc, dtype=np.float64)
    if kind == "occupancy":
        return np.count_nonzero(sc, axis=-1) / sc.shape[-1]
    return sc.mean(axis=-1)


def sector_key(sc: np.ndarray) -> np.ndarray:
    """``(..., S)`` column means, used to pre-align shifts."""
    return np.asarray(sc, dtype=np.float64).mean(axis=-2)


def shift_to_yaw(shift: np.ndarray, num_sectors: int = 60) -> np.ndarray:
    """Base-class yaw (degrees, CCW turn of the candidate) of C++ shifts; -1 gives nan."""
    shift = np.asarray(shift)
    step = 360.0 / num_sectors
    return np.where(shift >= 0, ((num_sectors - shift) % num_sectors) * step, np.nan)


def yaw_to_shift(yaw_deg: np.ndarray | float, num_sectors: int = 60) -> np.ndarray:
    """The C++ shift ``k`` (``query ~ np.roll(cand, k, axis=1)``) for a base-class yaw."""
    step = 360.0 / num_sectors
    return np.rint(-np.asarray(yaw_deg) / step).astype(np.int64) % num_sectors


class ScanContext(Descriptor):
    """Scan Context descriptor; see the module docstring for conventions."""

    name = "scan-context"
    label = "Scan Context"
    color = "#0072B2"
    params_type = ScanContextParams
    per_frame = True  # each scan's descriptor is computed from that scan alone
    symmetric = False
    # blocks are single-threaded NumPy / BLAS / FFT calls on whole chunks (the GIL is
    # released), and each pair's value does not depend on its block (kernels.py)
    threaded_blocks = True

    def __init__(self, params: ScanContextParams | None = None, preset: str = "custom"):
        super().__init__(params, preset)
        p = self.params
        self.dtype = np.dtype(
            [
                ("sc", np.float32, (p.rings, p.sectors)),
                ("ring_key", np.float64, (p.rings,)),
                ("sector_key", np.float64, (p.sectors,)),
            ]
        )
        # Exhaustive search sees every shift of both orders, and the exact
        # integer correlations satisfy S_ab(k) == S_ba(-k): d(a,b) == d(b,a)
        # bitwise. The sector-key window breaks ties by index, so it is not.
        self.symmetric = p.search == "exhaustive" or 2 * p.search_radius + 1 >= p.sectors

    # ----------------------------------------------------------------- extraction
    def compute(self, points: np.ndarray) -> np.ndarray:
        """Scan Context of ``(N, 3)`` points: a structured scalar (sc, ring_key, sector_key)."""
        points = np.asarray(points, dtype=np.float32)
        if points.ndim != 2 or points.shape[1] < 3:
            raise LirisError("points", f"expected an (N, 3) array, got shape {points.shape}")
        xyz = points[:, :3]
        if not np.isfinite(xyz).all():
            finite = np.isfinite(xyz).all(axis=1)
            warn("scan-context", f"dropped {int((~finite).sum())} non-finite points")
            xyz = xyz[finite]
        p = self.params
        if p.voxel_size > 0:
            # A voxel with a point beyond max_radius + its diagonal lies wholly
            # outside max_radius, so its centroid would be dropped anyway.
            reach = p.max_radius + p.voxel_size * math.sqrt(2.0) + 0.01
            cloud = voxel.voxel_centroids(xyz, p.voxel_size, reach) if len(xyz) else None
            if cloud is None:  # empty, or absurd outliers: the sort-based route
                x, y = xyz[:, 0].astype(np.float64), xyz[:, 1].astype(np.float64)
                cloud = voxel_downsample_numpy(xyz[x * x + y * y <= reach * reach], p.voxel_size)
            xyz = cloud
        sc = polar_context(np.ascontiguousarray(xyz), p)
        out = np.zeros((), dtype=self.dtype)
        out["sc"] = sc
        out["ring_key"] = ring_key(sc, p.ring_key)
        out["sector_key"] = sector_key(sc)
        return out

    # ------------------------------------------------------------------- matching
    def _records(self, descs: np.ndarray, what: str) -> np.ndarray:
        descs = np.asarray(descs)
        if descs.dtype != self.dtype:
            raise LirisError(what, f"not a {self.name} descriptor of these parameters")
        return descs.reshape(-1)

    def _side(self, descs: np.ndarray, role: str) -> kernels.Side:
        records = self._records(descs, "queries" if role == "query" else "database")
        keys = records["sector_key"] if self.params.search == "sector-key" else None
        return kernels.prepare(records["sc"], keys, role)

    def matcher(self, database: np.ndarray) -> ScanContextMatcher:
        """Prepare ``database`` once for many :meth:`ScanContextMatcher.pairwise` calls.

        Preparing a 4541-frame database takes tens of milliseconds; a caller
        that matches one query (or a small block) at a time against the same
        database should reuse a matcher. The numbers are the same as
        :meth:`pairwise`'s, which is built on it.
        """
        return ScanContextMatcher(self, self._side(database, "candidate"))

    def pairwise(self, queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Q, M)`` distances and yaws (degrees, base-class convention).

        The one code path behind :meth:`distance` and :meth:`distances` too,
        so all three agree bitwise. Memory is bounded by internal chunking
        (a few MB of temporaries besides the outputs and the prepared database).
        """
        return self.matcher(database).pairwise(queries)

    def distances(self, query: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One query against a stacked database: ``(M,)`` distances and yaws."""
        dist, yaw = self.pairwise(np.asarray(query).reshape(1), database)
        return dist[0], yaw[0]

    def distance(self, query: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        """Distance and yaw (degrees) between two descriptors.

        Compared directly by :mod:`.pair` (microseconds, the online use); the
        numbers are bitwise those of :meth:`pairwise` (tested).
        """
        q, c = np.asarray(query), np.asarray(candidate)
        if q.dtype is not self.dtype or c.dtype is not self.dtype:  # fast path: no copies
            q, c = self._records(q, "query"), self._records(c, "candidate")
        if q.size != 1 or c.size != 1:
            raise LirisError("distance", "expects one query and one candidate descriptor")
        q, c = q.reshape(()), c.reshape(())
        p = self.params
        dist, shift = pair.pair_distance(
            q["sc"], c["sc"], q["sector_key"], c["sector_key"], p.divide_by == "sectors",
            -1 if p.search == "exhaustive" else p.search_radius,
        )
        n = p.sectors
        # shift_to_yaw on one value, in Python floats (the same double arithmetic)
        yaw = ((n - shift) % n) * (360.0 / n) if shift >= 0 else math.nan
        return float(dist), float(yaw)

    # ------------------------------------------------------------------ retrieval
    def retrieve(
        self, db: np.ndarray, query: int, n_allowed: int, k: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Two-stage interface: the ``k`` frames of ``[0, n_allowed)`` nearest in ring key.

        A k-d tree over the ring keys of the allowed frames (as the C++ rebuilds
        it), returning ring-key distances too.
        """
        keys = self._records(db, "database")["ring_key"]
        k = min(int(k), int(n_allowed))
        if k < 1:
            return np.empty(0, dtype=np.int64), np.empty(0)
        dist, idx = cKDTree(keys[:n_allowed]).query(keys[query][None], k=k)
        return np.asarray(idx, dtype=np.int64).reshape(k), np.asarray(dist, float).reshape(k)


class ScanContextMatcher:
    """A database prepared for matching; made by :meth:`ScanContext.matcher`."""

    def __init__(self, descriptor: ScanContext, database: kernels.Side):
        self.descriptor = descriptor
        self._database = database

    def __len__(self) -> int:
        return len(self._database)

    def pairwise(self, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Q, M)`` distances and yaws of ``queries`` against the prepared database."""
        p = self.descriptor.params
        radius = None if p.search == "exhaustive" else p.search_radius
        dist, shift = kernels.pairwise_shift_distances(
            self.descriptor._side(queries, "query"),
            self._database,
            p.divide_by == "sectors",
            radius,
        )
        return dist, shift_to_yaw(shift, p.sectors)

    def distances(self, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M,)`` distances and yaws of one query against the prepared database."""
        dist, yaw = self.pairwise(np.asarray(query).reshape(1))
        return dist[0], yaw[0]
