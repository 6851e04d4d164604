"""ESF: PCL's rules checked by hand and against a scalar re-statement; sampling noise."""

from __future__ import annotations

import math
import warnings
from itertools import combinations
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor, vector_common
from lidar_iris_eval.descriptors.esf import (
    ESF,
    ESFParams,
    classify_lines,
    classify_triangles,
    esf_histogram,
    normalise,
    occupancy,
    pcl_round,
    sample_triangles,
    trace_lines,
    voxel_coords,
)
from lidar_iris_eval.errors import LirisError, LirisWarning

SAMPLES = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "samples" / "00"


def _scene(n: int = 1500, seed: int = 2) -> np.ndarray:
    """A small synthetic scene: ground plane, a wall and a pole, in metres."""
    rng = np.random.default_rng(seed)
    k = n // 3
    ground = np.c_[rng.uniform(-20, 20, (k, 2)), rng.normal(-1.7, 0.02, k)]
    wall = np.c_[rng.uniform(-15, 15, k), np.full(k, 8.0), rng.uniform(-1.7, 2.0, k)]
    ang = rng.uniform(0, 2 * np.pi, n - 2 * k)
    pole = np.c_[3 + 0.2 * np.cos(ang), -4 + 0.2 * np.sin(ang), rng.uniform(-1.7, 4, n - 2 * k)]
    return np.vstack([ground, wall, pole]).astype(np.float32)


# ---------------------------------------------------------------- scalar re-statement


def _lci(start, end, occ):
    """PCL's integer 3-D Bresenham walk, one step at a time (occ is a 64^3 array)."""
    cur = list(start)
    d = [e - s for s, e in zip(start, end, strict=True)]
    inc = [-1 if v < 0 else 1 for v in d]
    ln = [abs(v) for v in d]
    if ln[0] >= ln[1] and ln[0] >= ln[2]:
        major, minors = 0, (1, 2)
    elif ln[1] >= ln[0] and ln[1] >= ln[2]:
        major, minors = 1, (0, 2)
    else:
        major, minors = 2, (1, 0)
    err = {a: 2 * ln[a] - ln[major] for a in minors}
    count = inside = 0
    for _ in range(1, ln[major]):
        count += 1
        inside += int(occ[tuple(cur)])
        for a in minors:
            if err[a] > 0:
                cur[a] += inc[a]
                err[a] -= 2 * ln[major]
            err[a] += 2 * ln[a]
        cur[major] += inc[major]
    count += 1
    inside += int(occ[tuple(cur)])
    return inside, count


def _voxel(x: float) -> int:
    return int(math.floor(x) + 32) if x < 0 else int(math.ceil(x) + 31)


def _esf_scalar(pts: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """ESF of already-accepted triplets, written out triangle by triangle in float64."""
    vox = [[min(_voxel(float(c)), 63) for c in p] for p in pts]
    occ = np.zeros((64, 64, 64), bool)
    for v in vox:
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for dz in (-1, 0, 1):
                    q = (v[0] + dx, v[1] + dy, v[2] + dz)
                    if all(0 <= c < 64 for c in q):
                        occ[q] = True
    a3 = np.zeros((3, 64))
    d3_items, d2_items, ratio = [], [], np.zeros(64)
    for i1, i2, i3 in idx:
        p1, p2, p3 = (pts[i].astype(np.float64) for i in (i1, i2, i3))
        sides = [np.linalg.norm(p2 - p1), np.linalg.norm(p3 - p1), np.linalg.norm(p2 - p3)]
        s = sum(sides) / 2
        area2 = s * (s - sides[0]) * (s - sides[1]) * (s - sides[2])

        def angle_bin(u, w):
            c = abs(np.dot(u, w) / np.linalg.norm(u) / np.linalg.norm(w))
            return math.floor(math.acos(min(c, 1.0)) / (math.pi / 2) * 63 + 0.5)

        th = [angle_bin(p2 - p1, p3 - p1), angle_bin(p2 - p3, p3 - p1), angle_bin(p2 - p3, p2 - p1)]
        lines = [_lci(vox[a], vox[b], occ) for a, b in ((i1, i2), (i1, i3), (i2, i3))]
        for (inside, count), length in zip(lines, sides, strict=True):
            if inside >= count - 1:
                cls = 0
            elif inside <= 7:
                cls = 1
            else:
                cls = 2
                ratio[math.floor(inside / count * 63 + 0.5)] += 1
            d2_items.append((cls, length))
        in_sum = sum(x[0] for x in lines)
        cnt_sum = sum(x[1] for x in lines)
        tri = 1 if in_sum <= 21 else (0 if cnt_sum - in_sum < 4 else 2)
        for angle, opposite in zip(th, (lines[2][1], lines[0][1], lines[1][1]), strict=True):
            a3[tri, angle] += opposite / 32
        d3_items.append((tri, math.sqrt(math.sqrt(area2))))
    d3 = np.zeros((3, 64))
    top3 = max(v for _, v in d3_items)
    for cls, v in d3_items:
        d3[cls, math.floor(v / top3 * 63 + 0.5)] += 1
    d2 = np.zeros((3, 64))
    top2 = max(v for _, v in d2_items)
    for cls, v in d2_items:
        d2[cls, math.floor(v / top2 * 63 + 0.5)] += 1
    hist = np.concatenate([a3 * 0.5, d3 * [[0.5], [0.5], [1.0]], d2 * [[0.5], [2], [2]], [ratio]])
    hist = hist.ravel()
    return hist / hist.sum()


# ---------------------------------------------------------------- small exact cases


def test_pcl_round_is_floor_plus_half():
    x = np.array([0.5, 1.5, 2.5, 2.4999, 62.5], dtype=np.float32)
    np.testing.assert_array_equal(pcl_round(x), [1, 2, 3, 2, 63])  # numpy.round: 0, 2, 2, 2, 62


def test_voxel_rule_by_hand():
    pts = np.array([[-32.0, -0.5, 0.0], [-0.0, 0.5, 32.0], [31.2, -31.2, 32.0001]], np.float32)
    # x<0: floor(x)+32; else ceil(x)+31; clipped to 0..63
    np.testing.assert_array_equal(voxel_coords(pts), [[0, 31, 31], [31, 32, 63], [63, 0, 63]])


def test_occupancy_marks_3x3x3_clipped():
    occ = occupancy(np.array([[0, 0, 0], [10, 20, 30]])).reshape(64, 64, 64)
    assert occ.sum() == 8 + 27  # the corner voxel keeps 2x2x2 of its cube
    assert occ[9:12, 19:22, 29:32].all() and occ[:2, :2, :2].all()
    assert not occ[12, 20, 30] and not occ[2, 0, 0]


def test_line_walk_by_hand():
    occ = np.ones(64**3, bool)
    # (0,0,0)->(5,2,0): 5 voxels, start kept, end (5,2,0) dropped; y moves at steps 2 and 4
    inside, count = trace_lines(np.array([[0, 0, 0]]), np.array([[5, 2, 0]]), occ)
    assert (inside[0], count[0]) == (5, 5)
    grid = np.zeros((64, 64, 64), bool)
    for v in [(0, 0, 0), (1, 0, 0), (2, 1, 0), (3, 1, 0), (4, 2, 0)]:
        grid[v] = True
    inside, _ = trace_lines(np.array([[0, 0, 0]]), np.array([[5, 2, 0]]), grid.ravel())
    assert inside[0] == 5
    # same voxel: one voxel counted; unit step: start only
    inside, count = trace_lines(
        np.array([[3, 3, 3], [3, 3, 3]]), np.array([[3, 3, 3], [4, 3, 3]]), occ
    )
    np.testing.assert_array_equal(count, [1, 1])


def test_line_walk_matches_scalar_loop():
    rng = np.random.default_rng(4)
    occ3 = rng.random((64, 64, 64)) < 0.5
    start = rng.integers(0, 64, size=(400, 3))
    end = rng.integers(0, 64, size=(400, 3))
    end[:40] = start[:40]  # zero length
    end[40:80] = start[40:80] + rng.integers(-1, 2, size=(40, 3))  # unit steps
    end[80:120, 1] = start[80:120, 1] + (end[80:120, 0] - start[80:120, 0])  # x/y ties
    end = np.clip(end, 0, 63)
    inside, count = trace_lines(start, end, occ3.ravel())
    expected = np.array([_lci(list(s), list(e), occ3) for s, e in zip(start, end, strict=True)])
    np.testing.assert_array_equal(inside, expected[:, 0])
    np.testing.assert_array_equal(count, expected[:, 1])


def test_line_and_triangle_classes_by_hand():
    # IN if at most one empty voxel (even when <= 7 occupied), else OUT if <= 7, else MIXED
    inside = np.array([0, 4, 8, 7, 8, 30])
    count = np.array([1, 5, 9, 10, 10, 40])
    np.testing.assert_array_equal(classify_lines(inside, count), [0, 0, 0, 1, 2, 2])
    # OUT if <= 21 occupied; IN if fewer than 4 empty; else MIXED
    np.testing.assert_array_equal(
        classify_triangles(np.array([21, 22, 22, 40]), np.array([22, 25, 26, 60])), [1, 0, 2, 2]
    )


def test_histogram_matches_scalar_statement():
    pts = normalise(_scene(600))
    idx, *_ = sample_triangles(pts, 400, np.random.default_rng(9))
    expected = _esf_scalar(pts, idx)
    got = esf_histogram(_scene(600), 400, np.random.default_rng(9))
    np.testing.assert_allclose(got, expected, atol=2e-7)


def test_sampling_rejects_what_pcl_rejects():
    pts = normalise(_scene(300))
    idx, sides, heron, angles = sample_triangles(pts, 3000, np.random.default_rng(1))
    assert idx.shape == (3000, 3)
    assert (idx[:, 0] != idx[:, 1]).all() and (idx[:, 0] != idx[:, 2]).all()
    assert (idx[:, 1] != idx[:, 2]).all()
    assert (heron > 0.001).all() and ((angles >= 0) & (angles <= 63)).all()
    # every kept triangle's D2 sides are the point distances
    np.testing.assert_allclose(sides[:, 0], np.linalg.norm(pts[idx[:, 1]] - pts[idx[:, 0]], axis=1))


# ---------------------------------------------------------------- properties


def test_shape_sum_and_seed():
    pts = _scene()
    d = ESF(ESFParams(samples=3000, seed=5))
    h = d.compute(pts)
    assert h.shape == (640,) and h.dtype == np.float32 and (h >= 0).all()
    assert abs(float(h.sum(dtype=np.float64)) - 1.0) < 1e-6
    assert np.array_equal(h, d.compute(pts))  # same scan, same seed: same descriptor
    assert not np.array_equal(h, ESF(ESFParams(samples=3000, seed=6)).compute(pts))


def _noise_and_invariance(points: np.ndarray, samples: int) -> None:
    """Bound translation/scale effects by the seed-to-seed noise of the same cloud."""
    descs = [ESF(ESFParams(samples=samples, seed=s)) for s in range(4)]
    base = [d.compute(points) for d in descs]
    noise = [descs[0].distance(a, b)[0] for a, b in combinations(base, 2)]
    assert min(noise) > 0
    pts64 = points.astype(np.float64)
    for moved in (pts64 + [120.0, -35.5, 2.25], pts64 * 3.7, pts64 * 0.01):
        # same seed: the same triplets are drawn, so only rounding can differ
        assert descs[0].distance(base[0], descs[0].compute(moved))[0] <= 0.01 * min(noise)
        # another seed: no farther than the sampling noise itself
        assert descs[0].distance(base[0], descs[1].compute(moved))[0] <= 1.5 * max(noise)


def test_translation_and_scale_invariance_synthetic():
    _noise_and_invariance(_scene(), samples=4000)


def test_batched_forms_agree_bitwise(monkeypatch):
    d = ESF()
    rng = np.random.default_rng(12)
    queries = rng.dirichlet(np.ones(640), size=6).astype(np.float32)
    db = rng.dirichlet(np.ones(640), size=11).astype(np.float32)
    single = np.array([[d.distance(q, m)[0] for m in db] for q in queries])
    rows = np.array([d.distances(q, db)[0] for q in queries])
    monkeypatch.setattr(vector_common, "BLOCK_BYTES", 4 * 11 * 640 * 8)  # blocks of 4 queries
    pair, yaws = d.pairwise(queries, db)
    assert np.array_equal(single, rows) and np.array_equal(single, pair)
    assert np.isnan(yaws).all() and np.isnan(d.distance(queries[0], db[0])[1])
    assert d.symmetric and np.array_equal(single.T, d.pairwise(db, queries)[0])
    assert 0 <= single.min() and single.max() <= 2


def test_bad_input():
    with pytest.raises(LirisError):
        ESF().compute(np.zeros((2, 3), np.float32))
    with pytest.raises(LirisError):
        ESF().compute(np.zeros((5, 2), np.float32))
    # only two distinct positions: every triplet repeats a point (zero area)
    two = np.repeat(np.array([[0, 0, 0], [3, 1, 2]], np.float32), 20, axis=0)
    with pytest.raises(LirisError, match="non-degenerate"):
        ESF(ESFParams(samples=200)).compute(two)
    with pytest.raises(LirisError):
        ESF(ESFParams(samples=0))
    pts = _scene(400)
    bad = np.vstack([pts, [[np.nan, 0, 0]]]).astype(np.float32)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        h = ESF(ESFParams(samples=500)).compute(bad)
    assert any(issubclass(w.category, LirisWarning) for w in caught)
    assert np.array_equal(h, ESF(ESFParams(samples=500)).compute(pts))


def test_presets_load():
    for preset in ("paper", "reference"):
        d = get_descriptor("esf", preset=preset)
        assert isinstance(d, ESF) and d.params.samples == 20000


# ---------------------------------------------------------------- real KITTI scans


@pytest.fixture(scope="module")
def kitti():
    if not (SAMPLES / "velodyne" / "000094.bin").is_file():
        pytest.skip(f"real scans not found under {SAMPLES}")
    scans = {}
    for frame in (94, 95, 198):
        raw = np.fromfile(SAMPLES / "velodyne" / f"{frame:06d}.bin", dtype=np.float32)
        scans[frame] = raw.reshape(-1, 4)[:, :3]
    return scans


def test_real_neighbours_closer_on_average_over_seeds(kitti):
    near, far = [], []
    for seed in range(5):
        d = ESF(ESFParams(seed=seed))
        h = {k: d.compute(v) for k, v in kitti.items()}
        for v in h.values():
            assert abs(float(v.sum(dtype=np.float64)) - 1.0) < 1e-6
        near.append(d.distance(h[94], h[95])[0])
        far.append(d.distance(h[94], h[198])[0])
    assert np.mean(near) < np.mean(far)


def test_real_translation_and_scale_invariance(kitti):
    _noise_and_invariance(kitti[94], samples=20000)
