"""Scan Context: hand-checked binning and distances, a plain per-pair oracle, exactness
of the batched kernel, and the authors' numbers on real KITTI scans."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval import descriptors
from lidar_iris_eval.config import descriptor_preset_values
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.scan_context import (
    ScanContext,
    ScanContextParams,
    kernels,
    polar_angle_deg,
    polar_context,
    reference_loop,
    ring_key,
    sector_key,
    voxel_downsample,
    yaw_to_shift,
)
from lidar_iris_eval.errors import LirisError, LirisWarning

SAMPLES = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "samples" / "00"

# The authors' C++ on the shared scans (ALGORITHMS.md): distance with the
# sector-key search, its C++ shift, and the all-60-shift distance.
REFERENCE = {
    ("94", "95"): (0.1044, 0, 0.1044),
    ("94", "198"): (0.6106, 19, 0.4748),
    ("198", "199"): (0.1295, 0, 0.1295),
    ("94", "r90"): (0.0000, 45, 0.0000),
    ("94", "r180"): (0.0000, 30, 0.0000),
}


# --------------------------------------------------------------------------- helpers
def _rotate_z(points: np.ndarray, degrees: float) -> np.ndarray:
    """Counter-clockwise turn about +z, as the reference table's rN scans."""
    t = np.deg2rad(degrees)
    c, s = np.cos(t), np.sin(t)
    p = points.astype(np.float64)
    x = p[:, 0] * c - p[:, 1] * s
    y = p[:, 0] * s + p[:, 1] * c
    return np.stack([x, y, p[:, 2]], axis=1).astype(np.float32)


def _records(desc: ScanContext, sc: np.ndarray) -> np.ndarray:
    """Descriptor records built directly from ``(M, R, S)`` contexts."""
    sc = np.asarray(sc, dtype=np.float32)
    out = np.zeros(len(sc), dtype=desc.dtype)
    out["sc"] = sc
    out["ring_key"] = ring_key(sc, desc.params.ring_key)
    out["sector_key"] = sector_key(sc)
    return out


def _naive_per_shift(q: np.ndarray, c: np.ndarray, divide_by: str = "valid") -> np.ndarray:
    """d at every C++ shift k (q against roll(c, k)): the descriptor's reference loop."""
    return reference_loop.per_shift_distances(q, c, divide_by)


def _sector_key_start(q: np.ndarray, c: np.ndarray) -> int:
    """The C++ alignment: first shift minimising ||v_q - roll(v_c, s)||."""
    return reference_loop.sector_key_start(q, c)


def _naive(q, c, search: str, radius: int = 3, divide_by: str = "valid"):
    """The C++ search over ``_naive_per_shift``: (distance, C++ shift, all per-shift d)."""
    per_shift = _naive_per_shift(q, c, divide_by)
    n = len(per_shift)
    if search == "exhaustive":
        shifts = list(range(n))
    else:
        start = _sector_key_start(q, c)
        shifts = sorted({(start + j) % n for j in range(-radius, radius + 1)})
    best = min(shifts, key=lambda k: (per_shift[k], k))
    return per_shift[best], best, per_shift


def _random_contexts(rng, count, rings=20, sectors=60, empty_bins=0.3, empty_cols=0.1):
    """Non-negative max-height images with empty bins and some empty columns."""
    sc = rng.uniform(0.2, 6.0, size=(count, rings, sectors))
    sc[rng.random(sc.shape) < empty_bins] = 0.0
    sc[np.broadcast_to(rng.random((count, 1, sectors)) < empty_cols, sc.shape)] = 0.0
    return sc.astype(np.float32)


def _perturbed_rolls(rng, base, count):
    """Noisy copies of ``base`` contexts turned by random shifts: (copies, C++ shifts)."""
    idx = rng.integers(0, len(base), count)
    shifts = rng.integers(0, base.shape[2], count)
    out = np.empty((count, *base.shape[1:]), dtype=np.float32)
    for i in range(count):
        noisy = base[idx[i]] * rng.uniform(0.9, 1.1, base.shape[1:])
        noisy[rng.random(noisy.shape) < 0.05] = 0.0
        out[i] = np.roll(noisy, -shifts[i], axis=1)  # query ~ roll(copy, shift)
    return idx, out, shifts


@pytest.fixture(scope="module")
def real():
    """Real KITTI 00 scans 94, 95, 198, 199 (skip if ../shared is absent)."""
    files = {k: SAMPLES / "velodyne" / f"{int(k):06d}.bin" for k in ("94", "95", "198", "199")}
    if not all(f.is_file() for f in files.values()):
        pytest.skip("../shared/data/kitti/samples/00 is not available")
    return {
        k: np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for k, f in files.items()
    }


# ------------------------------------------------------------------ extraction pieces
def test_polar_angle_matches_atan2_and_quadrants():
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-50, 50, (2, 2000)).astype(np.float32)
    expected = np.degrees(np.arctan2(y.astype(np.float64), x)) % 360.0
    got = polar_angle_deg(x, y).astype(np.float64)
    diff = np.abs(got - expected)
    assert np.all(np.minimum(diff, 360 - diff) < 1e-4)
    axes = polar_angle_deg(np.float32([1, 0, -1, 0]), np.float32([0, 1, 0, -1]))
    assert np.allclose(axes, [0, 90, 180, 270])
    assert polar_angle_deg(np.float32([1]), np.float32([-1e-9]))[0] > 359.9
    assert np.isnan(polar_angle_deg(np.float32([0]), np.float32([0]))[0])  # as the C++ xy2theta


def test_polar_context_bins_by_hand():
    p = ScanContextParams(voxel_size=0.0)
    a = np.deg2rad
    pts = np.array(
        [
            [4.0, 0.0, 0.5],  # r = 4 -> ring 0 (ceil(1) - 1); theta 0 -> sector 0
            [4.001, 0.0, -0.5],  # ring 1, sector 0: value -0.5 + 2 = 1.5
            [10 * np.cos(a(6.5)), 10 * np.sin(a(6.5)), 1.0],  # ring 2, sector 1
            [10 * np.cos(a(6.5)), 10 * np.sin(a(6.5)), 3.0],  # same bin, larger z wins
            [80.0, 0.0, 0.0],  # r = 80 kept, ring 19
            [80.01, 0.0, 9.0],  # beyond 80 m: dropped
            [30.0, -1e-3, 0.0],  # just below +x: sector 59, ring 7
            [0.0, 0.0, 4.0],  # theta NaN in the C++ -> sector 0, ring 0
        ],
        dtype=np.float32,
    )
    sc = polar_context(pts, p)
    expected = np.zeros((20, 60), np.float32)
    expected[0, 0] = 6.0  # max(0.5 + 2, 4 + 2)
    expected[1, 0] = 1.5
    expected[2, 1] = 5.0
    expected[19, 0] = 2.0
    expected[7, 59] = 2.0
    np.testing.assert_array_equal(sc, expected)


def test_voxel_grid_faces_at_leaf_multiples_and_means():
    pts = np.array(
        [[0.1, 0.1, 0.1], [0.3, 0.2, 0.4], [0.49, 0.0, 0.0], [0.51, 0.0, 0.0], [-0.01, 0.0, 0.0]],
        dtype=np.float32,
    )
    out = voxel_downsample(pts, 0.5).astype(np.float64)
    out = out[np.argsort(out[:, 0])]
    # 0.1, 0.3 and 0.49 share the voxel [0, 0.5)^3; 0.51 and -0.01 are alone
    expected = [[-0.01, 0.0, 0.0], [0.89 / 3, 0.1, 0.5 / 3], [0.51, 0.0, 0.0]]
    np.testing.assert_allclose(out, expected, atol=1e-6)


def test_voxel_grid_matches_dictionary_grouping():
    rng = np.random.default_rng(2)
    pts = rng.uniform(-3, 3, (600, 3)).astype(np.float32)
    groups: dict[tuple, list] = {}
    for p in pts.astype(np.float64):
        groups.setdefault(tuple(np.floor(p / 0.5).astype(int)), []).append(p)
    expected = np.array(sorted(np.mean(v, axis=0).tolist() for v in groups.values()))
    got = voxel_downsample(pts, 0.5).astype(np.float64)
    got = got[np.lexsort(got.T[::-1])]
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_keys_by_hand():
    sc = np.array([[1.0, 0.0, 3.0], [0.0, 0.0, 2.0]])
    np.testing.assert_allclose(ring_key(sc, "mean"), [4 / 3, 2 / 3])
    np.testing.assert_allclose(ring_key(sc, "occupancy"), [2 / 3, 1 / 3])
    np.testing.assert_allclose(sector_key(sc), [0.5, 0.0, 2.5])


def test_compute_layout_and_input_checks():
    desc = get_descriptor("scan-context")
    rng = np.random.default_rng(3)
    pts = rng.uniform(-40, 40, (5000, 3)).astype(np.float32)
    d = desc.compute(pts)
    assert d.shape == () and d["sc"].shape == (20, 60) and d["sc"].dtype == np.float32
    np.testing.assert_allclose(d["ring_key"], d["sc"].astype(np.float64).mean(axis=1))
    np.testing.assert_allclose(d["sector_key"], d["sc"].astype(np.float64).mean(axis=0))
    with pytest.raises(LirisError):
        desc.compute(np.zeros((10, 2), np.float32))
    bad = pts.copy()
    bad[:7, 1] = np.nan
    with pytest.warns(LirisWarning, match="7 non-finite"):
        d_bad = desc.compute(bad)
    np.testing.assert_array_equal(d_bad["sc"], desc.compute(pts[7:])["sc"])
    empty = desc.compute(np.zeros((0, 3), np.float32))
    assert not empty["sc"].any()
    dist, yaw = desc.distance(empty, d)
    assert math.isnan(dist) and math.isnan(yaw)


def test_params_validation_and_presets():
    with pytest.raises(LirisError, match="ring_key"):
        ScanContextParams(ring_key="median")
    with pytest.raises(LirisError):
        get_descriptor("scan-context", no_such_key=1)
    assert get_descriptor("scan-context").preset == "reference"  # the first preset
    folder = Path(descriptors.__file__).parent / "scan_context" / "presets.yaml"
    name, _ = descriptor_preset_values("scan-context", None, path=folder)
    assert name == "reference"
    ref = get_descriptor("scan-context", "reference").params
    assert (ref.rings, ref.sectors, ref.max_radius, ref.lidar_height) == (20, 60, 80.0, 2.0)
    assert (ref.voxel_size, ref.search, ref.search_radius) == (0.5, "sector-key", 3)
    assert ref.ring_key == "mean"
    assert get_descriptor("scan-context", "exhaustive").params.search == "exhaustive"
    paper = get_descriptor("scan-context", "paper")
    assert (paper.params.ring_key, paper.params.divide_by) == ("occupancy", "sectors")
    assert paper.symmetric and not get_descriptor("scan-context").symmetric


# ------------------------------------------------------------------------- distances
def test_distance_by_hand_and_yaw_convention():
    desc = ScanContext(ScanContextParams(rings=2, sectors=4, search="exhaustive"))
    q = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 1.0, 0.0]])  # last column empty
    c = np.array([[3.0, 0.0, 2.0, 0.0], [4.0, 0.0, 0.0, 0.0]])
    # C++ shift k compares q with roll(c, k): valid columns and cosines by hand
    #   k=0: cols 0, 2: cos(q0,c0)=0.6, cos(q2,c2)=1/sqrt2      -> 1 - (0.6 + 0.70711)/2
    #   k=1: roll = [0,(3,4),0,(2,0)]: col 1: 0.8               -> 0.2
    #   k=2: roll = [(2,0),0,(3,4),0]: col 0: 1, col 2: 7/(5 sqrt2) -> 1 - (1 + 0.98995)/2
    #   k=3: roll = [0,(2,0),0,(3,4)]: col 1: 0                 -> 1
    expected = {
        0: 1 - (0.6 + 1 / math.sqrt(2)) / 2,
        1: 0.2,
        2: 1 - (1 + 7 / (5 * math.sqrt(2))) / 2,
        3: 1.0,
    }
    best_k = min(expected, key=expected.get)
    dist, yaw = desc.distance(*_records(desc, np.stack([q, c])))
    assert dist == pytest.approx(expected[best_k], abs=2e-5)
    assert best_k == 2 and yaw == 180.0
    # candidate = query turned one sector (90 deg) counter-clockwise
    turned = np.roll(q, 1, axis=1)
    dist, yaw = desc.distance(*_records(desc, np.stack([q, turned])))
    assert dist < 1e-4 and yaw == 90.0 and yaw_to_shift(yaw, 4) == 3


@pytest.mark.parametrize("preset", ["reference", "exhaustive", "paper"])
def test_kernel_matches_plain_per_pair_oracle(preset):
    desc = get_descriptor("scan-context", preset)
    p = desc.params
    rng = np.random.default_rng(4)
    base = _random_contexts(rng, 6)
    _, rolled, _ = _perturbed_rolls(rng, base, 6)
    sc = np.concatenate([base, rolled])
    recs = _records(desc, sc)
    dist, yaw = desc.pairwise(recs, recs)
    search = "exhaustive" if p.search == "exhaustive" else "sector-key"
    checked = 0
    for i in range(len(sc)):
        for j in range(len(sc)):
            d_ref, k_ref, per_shift = _naive(sc[i], sc[j], search, p.search_radius, p.divide_by)
            assert dist[i, j] == pytest.approx(d_ref, abs=2e-5)
            # compare shifts only where the oracle's minimum is clear of near-ties
            runner_up = np.sort(np.delete(per_shift, k_ref))[0]
            if search == "exhaustive" and runner_up - d_ref > 1e-4:
                assert yaw_to_shift(yaw[i, j]) == k_ref
                checked += 1
    assert search != "exhaustive" or checked > 50


def test_exhaustive_never_worse_and_equal_inside_window():
    rng = np.random.default_rng(5)
    ref = get_descriptor("scan-context", "reference")
    exh = get_descriptor("scan-context", "exhaustive")
    base = _random_contexts(rng, 10, empty_cols=0.0)
    idx, copies, _ = _perturbed_rolls(rng, base, 25)
    unrelated = _random_contexts(rng, 25, empty_cols=0.0)
    queries = np.concatenate([base[idx], base[rng.integers(0, 10, 25)]])
    cands = np.concatenate([copies, unrelated])  # 50 pairs: 25 turned copies, 25 unrelated
    q_rec, c_rec = _records(ref, queries), _records(ref, cands)
    d_ref = np.array([ref.distance(q_rec[i], c_rec[i])[0] for i in range(50)])
    d_exh, yaw_exh = np.array([exh.distance(q_rec[i], c_rec[i]) for i in range(50)]).T
    assert np.all(d_exh <= d_ref)
    inside = 0
    for i in range(50):
        start = _sector_key_start(queries[i], cands[i])
        k = int(yaw_to_shift(yaw_exh[i]))
        if min((k - start) % 60, (start - k) % 60) <= 3:
            assert d_exh[i] == d_ref[i]
            inside += 1
    assert inside >= 25  # every turned copy is found by its sector key
    assert np.any(d_exh < d_ref)  # and the window does miss some unrelated pairs


@pytest.mark.parametrize("preset", ["reference", "exhaustive"])
def test_exact_ties_go_to_the_smallest_shift(preset):
    # columns repeating with period 2: every even shift matches exactly, so the
    # integer-exact correlations tie bitwise; the C++ keeps the first in sorted
    # order, shift 0 (the sector-key window is {57, ..., 59, 0, ..., 3}).
    desc = get_descriptor("scan-context", preset)
    pair = np.random.default_rng(10).uniform(0.5, 5.0, (20, 2))
    sc = np.tile(pair, (1, 30))[None].repeat(2, axis=0)
    dist, yaw = desc.distance(*_records(desc, sc))
    assert yaw == 0.0 and dist < 1e-5


@pytest.mark.parametrize("preset", ["reference", "exhaustive", "paper"])
def test_single_batched_pairwise_bitwise_equal(preset):
    desc = get_descriptor("scan-context", preset)
    rng = np.random.default_rng(6)
    sc = _random_contexts(rng, 23)
    sc[3] = 0.0  # an empty scan
    sc[4, :, 1:] = 0.0  # a single valid column
    recs = _records(desc, sc)
    queries, database = recs[:7], recs[7:]
    dist, yaw = desc.pairwise(queries, database)
    single = np.array([[desc.distance(q, m) for m in database] for q in queries])
    assert np.array_equal(dist, single[..., 0], equal_nan=True)
    assert np.array_equal(yaw, single[..., 1], equal_nan=True)
    for i, q in enumerate(queries):
        row_d, row_y = desc.distances(q, database)
        assert np.array_equal(row_d, dist[i], equal_nan=True)
        assert np.array_equal(row_y, yaw[i], equal_nan=True)
    # a reused matcher, and tiny inner chunks (other BLAS shapes), give the same bits
    matcher = desc.matcher(database)
    assert np.array_equal(matcher.pairwise(queries)[0], dist, equal_nan=True)
    assert np.array_equal(matcher.distances(queries[2])[1], yaw[2], equal_nan=True)
    prepared = desc._side(queries, "query"), desc._side(database, "candidate")
    radius = None if desc.params.search == "exhaustive" else desc.params.search_radius
    for chunk_pairs, chunk_m in [(3, 1), (40, 5), (10**6, 10**6)]:
        d2, _ = kernels.pairwise_shift_distances(
            *prepared, desc.params.divide_by == "sectors", radius, chunk_pairs, chunk_m
        )
        assert np.array_equal(d2, dist, equal_nan=True)
    assert np.isnan(dist[3]).all()


def test_exhaustive_is_symmetric_bitwise():
    desc = get_descriptor("scan-context", "exhaustive")
    recs = _records(desc, _random_contexts(np.random.default_rng(7), 12))
    d_ab, yaw_ab = desc.pairwise(recs[:5], recs[5:])
    d_ba, yaw_ba = desc.pairwise(recs[5:], recs[:5])
    assert desc.symmetric
    assert np.array_equal(d_ab, d_ba.T)


def test_rounding_margin_and_inverse_dft():
    rng = np.random.default_rng(8)
    for n in (60, 7):
        spec = np.fft.rfft(rng.standard_normal((5, n)))
        g = kernels.inverse_dft_matrix(n)
        inter = np.stack([spec.real, spec.imag], axis=2).reshape(5, -1)
        np.testing.assert_allclose(inter @ g.T, np.fft.irfft(spec, n), atol=1e-12)
    # the float route must land well within 0.5 of the integer correlation
    sc = _random_contexts(rng, 40, empty_bins=0.0, empty_cols=0.0)
    sc[:20] *= rng.uniform(0, 1, (20, 20, 1)) ** 8  # very uneven columns
    query, cand = kernels.prepare(sc, None, "query"), kernels.prepare(sc, None, "candidate")
    a = np.concatenate(query.columns, axis=1)
    cross = np.matmul(a, cand.columns[0])
    raw = kernels.inverse_dft_matrix(60) @ cross.reshape(62, -1)
    assert np.abs(raw - np.rint(raw)).max() < 0.01
    unit, _ = kernels.quantised_unit_columns(sc)
    exact = np.einsum("rc,rc->", unit[0], np.roll(unit[1], 5, axis=1))
    assert np.rint(raw.reshape(60, 40, 40)[5, 0, 1]) == exact


def test_candidates_are_nearest_ring_keys():
    desc = get_descriptor("scan-context")
    recs = _records(desc, _random_contexts(np.random.default_rng(9), 60))
    keys = recs["ring_key"]
    for query, n_allowed in ((59, 52), (40, 30), (12, 3)):
        got, dist = desc.retrieve(recs, query, n_allowed, 10)
        k = min(10, n_allowed)
        assert got.shape == (k,) and got.dtype == np.int64
        d = np.linalg.norm(keys[:n_allowed] - keys[query], axis=1)
        expected = np.argsort(d, kind="stable")[:k]
        np.testing.assert_array_equal(got, expected)
        np.testing.assert_allclose(dist, d[expected], rtol=1e-12)
    assert not hasattr(desc, "candidates")  # the legacy retrieval hook is gone (issue 39)


# ------------------------------------------------------------------------ real scans
def test_real_scans_match_authors_cpp(real):
    scans = dict(real)
    scans["r90"] = _rotate_z(real["94"], 90)
    scans["r180"] = _rotate_z(real["94"], 180)
    ref = get_descriptor("scan-context", "reference")
    exh = get_descriptor("scan-context", "exhaustive")
    descs = {k: ref.compute(v) for k, v in scans.items()}
    for (a, b), (d_cpp, shift_cpp, d_all) in REFERENCE.items():
        d, yaw = ref.distance(descs[a], descs[b])
        # 5e-5: the table's 4-decimal rounding; quantised cosines add ~2e-6
        assert abs(d - d_cpp) <= 5.5e-5, (a, b, d)
        assert yaw_to_shift(yaw) == shift_cpp
        assert abs(exh.distance(descs[a], descs[b])[0] - d_all) <= 5.5e-5
    assert ref.distance(descs["94"], descs["95"])[0] < ref.distance(descs["94"], descs["198"])[0]


def test_real_scan_turned_by_sector_multiples(real):
    desc = get_descriptor("scan-context", "reference")
    exh = get_descriptor("scan-context", "exhaustive")
    base = desc.compute(real["198"])
    for degrees in (6, 42, 96, 264, 354):
        turned = desc.compute(_rotate_z(real["198"], degrees))
        for d in (desc, exh):
            dist, yaw = d.distance(base, turned)
            assert dist < 0.02 and yaw == degrees


def test_real_voxel_grid_count_matches_dictionary(real):
    pts = real["95"][:20000]
    keys = {tuple(k) for k in np.floor(pts.astype(np.float64) / 0.5).astype(int)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(voxel_downsample(pts, 0.5)) == len(keys)
