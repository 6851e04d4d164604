"""ESF: Ensemble of Shape Functions (Wohlkinger and Vincze, 2011), as PCL computes it.

The cloud is centred and scaled so that its farthest point lies 32 units from
the centroid, then voxelised on a 64^3 grid in which every point marks its
voxel and the 26 neighbours as occupied. 20,000 random point triplets are
drawn; each contributes

* A3: its three (folded, <= 90 degree) angles,
* D2: its three side lengths,
* D3: the square root of its area,

and each side is traced through the grid (3-D Bresenham) to decide whether it
runs IN the surface, OUT of it, or MIXED. The ten 64-bin histograms
``[A3 in, out, mix | D3 in, out, mix | D2 in, out, mix | D2 mix ratio]``
are weighted ``[.5, .5, .5, .5, .5, 1, .5, 2, 2, 1]`` and normalised to sum
to 1, giving a 640-d float32 vector. Two descriptors are compared by the L1
distance, in ``[0, 2]`` (neither PCL nor the LiDAR Iris paper defines one);
yaw is not estimated.

Faithful to PCL's ``ESFEstimation`` (``features/impl/esf.hpp``), including
its quirks:

* rounding is ``pcl_round(x) = floor(x + 0.5)``, in float32 like PCL;
* voxel of coordinate ``x`` is ``floor(x) + 32`` if ``x < 0`` else
  ``ceil(x) + 31`` (clipped to the grid: PCL reads out of bounds when float
  rounding puts the farthest point just beyond 32);
* a traced side counts ``max(L_inf length, 1)`` voxels, start included, end
  excluded; it is IN if at most one of them is empty (so one-voxel sides are
  always IN), else OUT if at most 7 are occupied, else MIXED;
* a triangle is OUT if its sides cross at most 21 occupied voxels in total,
  else IN if fewer than 4 crossed voxels are empty, else MIXED; its A3
  angles are weighted by the voxel count of the opposite side / 32;
* triplets with a repeated index, squared Heron area <= 0.001 (in grid
  units) or a NaN angle are redrawn.

Randomness and reproducibility
------------------------------
PCL draws indices with ``rand() % N`` after ``srand(time(nullptr))`` on every
call, so PCL's ESF changes from one second to the next: on the shared KITTI
scans two runs differ by 0.10-0.21 L1, as much as two different places. Here
the generator is ``numpy.random.default_rng(seed)``, restarted for every scan,
so the same scan with the same ``seed`` always gives the same descriptor
(with a given NumPy: NEP 19 does not promise identical streams across NumPy
versions, so caches of ESF descriptors should not outlive a NumPy upgrade).
Matching glibc ``rand()`` is impractical, so PCL's exact histograms are not
reproduced. The sampling noise between seeds is of the same size as PCL's:
on the four shared KITTI scans, seed-to-seed L1 distances of one scan span
0.05-0.28 (median about 0.15), while neighbouring scans are 0.10-0.12 apart
and different places 0.14-0.20 (seed 0). Compare ESF results over several
seeds, and do not read single-scan differences below about 0.2 as signal.

Also inherited from the method: one far outlier rescales everything (a full
KITTI scan gives 2.5-4 m voxels), and the descriptor needs triangles of
non-zero area: a cloud without them (e.g. only two distinct positions) makes
PCL loop forever and raises a LirisError here. Exactly collinear points are
usually accepted, by PCL and here alike, because float32 Heron's formula
turns their rounding errors into areas above the threshold.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.esf import kernels
from lidar_iris_eval.descriptors.vector_common import finite_xyz
from lidar_iris_eval.descriptors.vector_kernels import pairwise_with_nan_yaws
from lidar_iris_eval.errors import LirisError

GRID = 64
HALF = GRID // 2
BINS = 64
#: effective weights of the ten histograms in PCL's output order
WEIGHTS = np.array([0.5, 0.5, 0.5, 0.5, 0.5, 1.0, 0.5, 2.0, 2.0, 1.0])
WEIGHTS.setflags(write=False)
#: squared-area threshold below which PCL redraws a triplet (grid units)
MIN_HERON = np.float32(0.001)
#: give up after this many draws per requested sample (degenerate clouds)
_MAX_DRAWS_PER_SAMPLE = 50
_STRIDES = np.array([GRID * GRID, GRID, 1], dtype=np.int64)


@dataclass(frozen=True)
class ESFParams:
    """Parameters of ESF.

    Attributes
    ----------
    samples : int
        Accepted point triplets per scan (PCL: 20,000).
    seed : int
        Seed of the per-scan random generator; the same scan and seed give
        the same descriptor.
    """

    samples: int = 20000
    seed: int = 0


def pcl_round(x: np.ndarray) -> np.ndarray:
    """PCL's rounding for non-negative values, ``floor(x + 0.5)`` in x's precision."""
    return np.floor(x + x.dtype.type(0.5))


def normalise(points: np.ndarray) -> np.ndarray:
    """Centre on the centroid and scale the farthest point to distance 32 (float32).

    The centroid (:func:`.kernels.column_means`, NumPy's float64 mean), centring,
    the farthest distance and the scaling are compiled
    (:func:`.kernels.centred_scaled`), bitwise equal to :func:`normalise_numpy`
    (tested).
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.dtype not in (np.float32, np.float64):
        return normalise_numpy(points)
    pts = np.ascontiguousarray(pts)
    mean = kernels.column_means(pts)
    out, max_dist = kernels.centred_scaled(pts, mean, float(HALF))
    if not max_dist > 0.0:
        raise LirisError("points", "ESF needs points that are not all identical")
    return out


def normalise_numpy(points: np.ndarray) -> np.ndarray:
    """The NumPy route of :func:`normalise`."""
    pts = np.asarray(points, dtype=np.float64)
    centred = pts - pts.mean(axis=0)
    max_dist = float(np.sqrt(np.max(np.einsum("ij,ij->i", centred, centred))))
    if not max_dist > 0.0:
        raise LirisError("points", "ESF needs points that are not all identical")
    return (centred * (HALF / max_dist)).astype(np.float32)


def voxel_coords(points: np.ndarray) -> np.ndarray:
    """PCL's voxel index per coordinate, ``(N, 3)`` int64 clipped to the grid.

    Compiled (:func:`.kernels.voxel_coords`) for float32 input;
    :func:`voxel_coords_numpy` is the reference it equals bitwise (tested).
    """
    points = np.asarray(points)
    if points.dtype == np.float32 and points.ndim == 2 and points.shape[1] == 3:
        return kernels.voxel_coords(np.ascontiguousarray(points), np.float32(HALF), GRID)
    return voxel_coords_numpy(points)


def voxel_coords_numpy(points: np.ndarray) -> np.ndarray:
    """The NumPy route of :func:`voxel_coords`."""
    vox = np.where(points < 0, np.floor(points) + HALF, np.ceil(points) + (HALF - 1))
    return np.clip(vox, 0, GRID - 1).astype(np.int64)


def occupancy(vox: np.ndarray) -> np.ndarray:
    """Flat ``GRID**3`` bool grid: each point's voxel and its 26 neighbours set.

    The 3x3x3 marking is a cube dilation, done as three 1-D dilations
    instead of 27 writes per point.
    """
    grid = np.zeros((GRID, GRID, GRID), dtype=bool)
    grid[vox[:, 0], vox[:, 1], vox[:, 2]] = True
    for axis in range(3):
        src = grid.copy()
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(None, -1), slice(1, None)
        grid[tuple(hi)] |= src[tuple(lo)]
        grid[tuple(lo)] |= src[tuple(hi)]
    return grid.ravel()


def trace_lines(start: np.ndarray, end: np.ndarray, occupied: np.ndarray):
    """Walk PCL's 3-D Bresenham line from each start voxel towards its end voxel.

    The compiled loop of :mod:`.kernels`; :func:`trace_lines_numpy` (same
    parameters and results, bitwise, tested) documents the closed form.
    """
    return kernels.trace_lines(
        np.ascontiguousarray(start, dtype=np.int64),
        np.ascontiguousarray(end, dtype=np.int64),
        np.ascontiguousarray(occupied, dtype=bool),
        GRID,
    )


def trace_lines_numpy(start: np.ndarray, end: np.ndarray, occupied: np.ndarray):
    """Walk PCL's 3-D Bresenham line from each start voxel towards its end voxel (NumPy).

    Parameters
    ----------
    start, end : (L, 3) int arrays of voxel coordinates
    occupied : (GRID**3,) bool, from :func:`occupancy`

    Returns
    -------
    inside : (L,) int64, occupied voxels visited
    count : (L,) int64, voxels visited, ``max(L_inf length, 1)``

    Notes
    -----
    After ``k`` steps along the major axis (length ``M``), PCL's error-term
    loop has moved an axis of length ``m`` by ``floor((2*m*k + M - 1) / (2*M))``
    voxels (this is exact for the major axis too, giving ``k``). That closed
    form lets all steps of all lines be evaluated at once.
    """
    delta = end - start
    length = np.abs(delta)
    count = np.maximum(length.max(axis=1), 1)
    first = np.cumsum(count) - count
    total = int(count.sum())
    step = np.arange(total, dtype=np.int64) - np.repeat(first, count)
    numer0 = np.repeat(count - 1, count)
    denom = np.repeat(2 * count, count)
    signed_strides = np.where(delta < 0, -_STRIDES, _STRIDES)
    flat = np.repeat(start @ _STRIDES, count)
    for axis in range(3):
        offset = np.repeat(2 * length[:, axis], count) * step
        offset += numer0
        offset //= denom
        offset *= np.repeat(signed_strides[:, axis], count)
        flat += offset
    inside = np.add.reduceat(occupied[flat].astype(np.int64), first)
    return inside, count


def classify_lines(inside: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Line class as PCL codes it: 0 IN, 1 OUT, 2 MIXED."""
    return np.where(inside >= count - 1, 0, np.where(inside <= 7, 1, 2))


def classify_triangles(inside_sum: np.ndarray, count_sum: np.ndarray) -> np.ndarray:
    """Triangle class: 1 OUT (<= 21 occupied), else 0 IN (< 4 empty), else 2 MIXED."""
    return np.where(inside_sum <= 21, 1, np.where(count_sum - inside_sum < 4, 0, 2))


def _triangle_geometry(p1, p2, p3):
    """Sides (12, 13, 23), squared Heron area and folded angle bins, in float32."""
    v21, v31, v23 = p2 - p1, p3 - p1, p2 - p3
    a = np.sqrt(np.einsum("ij,ij->i", v21, v21))
    b = np.sqrt(np.einsum("ij,ij->i", v31, v31))
    c = np.sqrt(np.einsum("ij,ij->i", v23, v23))
    s = (a + b + c) * np.float32(0.5)
    heron = s * (s - a) * (s - b) * (s - c)
    with np.errstate(invalid="ignore", divide="ignore"):
        u21, u31, u23 = v21 / a[:, None], v31 / b[:, None], v23 / c[:, None]
        half_pi, top = np.float32(np.pi / 2), np.float32(BINS - 1)
        cosines = [
            np.einsum("ij,ij->i", u21, u31),  # angle at p1
            np.einsum("ij,ij->i", u23, u31),  # angle at p3
            np.einsum("ij,ij->i", u23, u21),  # angle at p2
        ]
        # |cos| > 1 from rounding gives NaN, as in PCL, and the triplet is redrawn
        angles = np.stack(
            [pcl_round(np.arccos(np.abs(cs)) / half_pi * top) for cs in cosines], axis=1
        )
    return np.stack([a, b, c], axis=1), heron, angles


def _triangle_geometry_compiled(points: np.ndarray, idx: np.ndarray):
    """:func:`_triangle_geometry` of ``points[idx]``: the gather, sides, areas and
    cosines compiled (:func:`.kernels.triangle_geometry`), the ``arccos`` and
    its binning in NumPy (NumPy's float32 ``arccos`` may be a SIMD routine
    that libm's would not match). Bitwise the same arrays (tested)."""
    sides, heron, cosines = kernels.triangle_geometry(points, idx)
    half_pi, top = np.float32(np.pi / 2), np.float32(BINS - 1)
    with np.errstate(invalid="ignore"):
        np.abs(cosines, out=cosines)
        angles = np.arccos(cosines, out=cosines)
        angles /= half_pi
        angles *= top
        angles += np.float32(0.5)
        np.floor(angles, out=angles)
    return sides, heron, angles


def _draw_batches(points: np.ndarray, samples: int, rng: np.random.Generator,
                  compiled: bool = True):
    """Draw batches of triplets until ``samples`` are valid, redrawing as PCL would.

    Yields ``(idx, sides, heron, angles, ok)`` per batch, ``ok`` marking the
    triplets PCL accepts (three distinct points, area above :data:`MIN_HERON`,
    finite angles). Both routes of :func:`sample_triangles` draw through here,
    so they consume the generator identically and keep the same triplets; each
    keeps what it needs of a batch. Raises the one error line once
    ``_MAX_DRAWS_PER_SAMPLE * samples`` draws have not found enough.
    ``compiled`` picks :func:`_triangle_geometry_compiled` (float32 points
    only) over the NumPy :func:`_triangle_geometry`; both give the same arrays.
    """
    compiled = compiled and points.dtype == np.float32 and points.flags.c_contiguous
    n = len(points)
    have = drawn = 0
    while have < samples:
        if drawn >= _MAX_DRAWS_PER_SAMPLE * samples:
            raise LirisError(
                "points",
                f"ESF found only {have} of {samples} non-degenerate triangles in "
                f"{drawn} draws; the points are (nearly) coincident or collinear",
            )
        batch = max(1024, int(1.1 * (samples - have)))
        idx = rng.integers(0, n, size=(batch, 3))
        drawn += batch
        if compiled:
            sides, heron, angles = _triangle_geometry_compiled(points, idx)
        else:
            sides, heron, angles = _triangle_geometry(*(points[idx[:, j]] for j in range(3)))
        ok = (idx[:, 0] != idx[:, 1]) & (idx[:, 0] != idx[:, 2]) & (idx[:, 1] != idx[:, 2])
        ok &= heron > MIN_HERON
        ok &= np.isfinite(angles).all(axis=1)
        yield idx, sides, heron, angles, ok
        have += int(ok.sum())


def sample_triangles(points: np.ndarray, samples: int, rng: np.random.Generator):
    """Draw ``samples`` valid triplets, redrawing the ones PCL would reject.

    Returns ``(idx (S, 3), sides (S, 3), heron (S,), angle_bins (S, 3) int64)``,
    in draw order. The geometry of each batch is computed once and kept for
    the accepted triplets (element-wise float32 maths, so the values equal
    :func:`sample_triangles_previous`, which recomputed them: tested bitwise).
    """
    kept = [(idx[ok], sides[ok], heron[ok], angles[ok])
            for idx, sides, heron, angles, ok in _draw_batches(points, samples, rng)]
    idx, sides, heron, angles = (np.concatenate([k[f] for k in kept])[:samples]
                                 for f in range(4))
    return idx, sides, heron, angles.astype(np.int64)


def sample_triangles_previous(points: np.ndarray, samples: int, rng: np.random.Generator):
    """The previous route of :func:`sample_triangles` (geometry recomputed for the kept).

    Returns ``(idx (S, 3), sides (S, 3), heron (S,), angle_bins (S, 3) int64)``,
    in draw order. Kept as the benchmark's baseline (scripts/bench_extraction.py):
    it keeps only the indices of each batch, as it always did.
    """
    kept = [idx[ok] for idx, _, _, _, ok in _draw_batches(points, samples, rng, compiled=False)]
    idx = np.concatenate(kept)[:samples]
    sides, heron, angles = _triangle_geometry(*(points[idx[:, j]] for j in range(3)))
    return idx, sides, heron, angles.astype(np.int64)


def esf_histogram(points: np.ndarray, samples: int, rng: np.random.Generator) -> np.ndarray:
    """The 640-d ESF of an ``(N, 3)`` cloud (any frame, any scale).

    Sampling stays in NumPy (it owns the random stream); the line tracing and
    the four histograms are one compiled pass (:func:`.kernels.raw_histogram`)
    instead of ``3 S``-long temporaries, bitwise equal to
    :func:`esf_histogram_numpy` (tested on real and simulated scans).
    """
    pts = normalise(points)
    vox = voxel_coords(pts)
    occupied = occupancy(vox)
    idx, sides, heron, angle_bins = sample_triangles(pts, samples, rng)
    hist = kernels.raw_histogram(vox.astype(np.int8), np.ascontiguousarray(idx, dtype=np.int64),
                                 occupied, GRID,
                                 np.ascontiguousarray(sides), np.ascontiguousarray(heron),
                                 np.ascontiguousarray(angle_bins), BINS)
    hist *= np.repeat(WEIGHTS, BINS)
    return (hist / hist.sum()).astype(np.float32)


def esf_histogram_numpy(points: np.ndarray, samples: int, rng: np.random.Generator
                        ) -> np.ndarray:
    """The NumPy route of :func:`esf_histogram` (the reference it equals bitwise)."""
    pts = normalise(points)
    vox = voxel_coords(pts)
    occupied = occupancy(vox)
    idx, sides, heron, angle_bins = sample_triangles(pts, samples, rng)

    # sides in PCL's order: 1->2, 1->3, 2->3, all lines of a triplet together
    corners = vox[idx]  # one random gather of the corners' voxels, (S, 3 corners, 3)
    starts = corners[:, [0, 0, 1]].reshape(-1, 3)
    ends = corners[:, [1, 2, 2]].reshape(-1, 3)
    inside, count = trace_lines(starts, ends, occupied)
    line_class = classify_lines(inside, count)
    inside3, count3 = inside.reshape(-1, 3), count.reshape(-1, 3)
    tri_class = classify_triangles(inside3.sum(axis=1), count3.sum(axis=1))

    hist = np.zeros(10 * BINS)
    # A3: angles at p1, p3, p2 weighted by the voxel count of the opposite side
    opposite = count3[:, [2, 0, 1]] / 32.0
    hist += np.bincount(
        (tri_class[:, None] * BINS + angle_bins).ravel(),
        weights=opposite.ravel(),
        minlength=10 * BINS,
    )
    # D3: sqrt(area), binned against the largest sample
    d3 = np.sqrt(np.sqrt(heron))
    d3_bin = pcl_round(d3 / d3.max() * np.float32(BINS - 1)).astype(np.int64)
    hist += np.bincount((3 + tri_class) * BINS + d3_bin, minlength=10 * BINS)
    # D2: side lengths, binned against the longest side
    d2 = sides.ravel()
    d2_bin = pcl_round(d2 / d2.max() * np.float32(BINS - 1)).astype(np.int64)
    hist += np.bincount((6 + line_class) * BINS + d2_bin, minlength=10 * BINS)
    # mixed lines: fraction of occupied voxels
    mixed = line_class == 2
    ratio = inside[mixed].astype(np.float32) / count[mixed].astype(np.float32)
    ratio_bin = pcl_round(ratio * np.float32(BINS - 1)).astype(np.int64)
    hist += np.bincount(9 * BINS + ratio_bin, minlength=10 * BINS)

    hist *= np.repeat(WEIGHTS, BINS)
    return (hist / hist.sum()).astype(np.float32)


def l1_rows(query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """L1 distance of ``query`` to each row of ``rows`` (any leading shape).

    All distance forms go through this one float64 reduction along a
    contiguous last axis, so they agree bit for bit.
    """
    diff = np.asarray(rows, dtype=np.float64) - np.asarray(query, dtype=np.float64)
    np.abs(diff, out=diff)
    return np.sum(diff, axis=-1)


class ESF(Descriptor):
    """ESF global descriptor: 640-d float32 histogram, L1 distance, no yaw."""

    name = "esf"
    label = "ESF"
    color = "#CC79A7"
    params_type = ESFParams
    per_frame = True  # the triplets' generator restarts from the seed for every scan
    symmetric = True  # |a - b| == |b - a| exactly

    def __init__(self, params: ESFParams | None = None, preset: str = "custom"):
        super().__init__(params, preset)
        source = f"esf preset {preset}"
        if self.params.samples < 1:
            raise LirisError(
                source, f"samples must be a positive integer, got {self.params.samples}"
            )
        if self.params.seed < 0:
            raise LirisError(source, f"seed must be a non-negative integer, got {self.params.seed}")

    def compute(self, points: np.ndarray) -> np.ndarray:
        """Describe one scan: ``(N, 3)`` points to a ``(640,)`` float32 histogram."""
        pts = finite_xyz(points, minimum=3, dtype=np.asarray(points).dtype, method="ESF")
        rng = np.random.default_rng(self.params.seed)
        return esf_histogram(pts, self.params.samples, rng)

    def distance(self, query: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        """L1 distance (``[0, 2]``) and ``nan`` yaw."""
        return float(l1_rows(query, np.asarray(candidate)[None, :])[0]), float("nan")

    def distances(self, query: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(M,)`` L1 distances of ``query`` to each database row, and nan yaws."""
        dists = l1_rows(query, database).reshape(len(database))
        return dists, np.full(len(database), np.nan)

    def pairwise(self, queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(Q, M)`` L1 distances, each bitwise :func:`l1_rows`'s."""
        # compiled, on every numba thread (tests/test_vector_kernels.py)
        return pairwise_with_nan_yaws(queries, database, "l1")
