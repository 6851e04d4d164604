"""M2DP: hand-checked pieces, properties, and the authors' numbers on real KITTI scans."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor, vector_common
from lidar_iris_eval.descriptors.m2dp import (
    M2DP,
    M2DPParams,
    descriptor_from_signature,
    pca_align,
    projection_planes,
    signature_matrix,
)
from lidar_iris_eval.descriptors.m2dp.descriptor import signature_matrix_fast
from lidar_iris_eval.errors import LirisError, LirisWarning

SAMPLES = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "samples" / "00"

# L2 distances measured with the authors' M2DP.m under Octave (ALGORITHMS.md),
# printed to 4 decimals.
REFERENCE = {
    ("94", "95"): 0.0457,
    ("94", "198"): 0.2085,
    ("198", "199"): 0.0604,
    ("94", "r90"): 0.2296,
    ("94", "r180"): 0.4293,
}


def _rotate_z(points: np.ndarray, degrees: float) -> np.ndarray:
    """Counter-clockwise turn about +z, as the reference table's rN scans."""
    t = np.deg2rad(degrees)
    c, s = np.cos(t), np.sin(t)
    p = points.astype(np.float64)
    return np.stack([p[:, 0] * c - p[:, 1] * s, p[:, 0] * s + p[:, 1] * c, p[:, 2]], axis=1)


def _box_cloud(n: int = 3000, seed: int = 7) -> np.ndarray:
    """Points on the faces of a 12 x 6 x 2 box: distinct variances along x, y, z."""
    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, size=(n, 3)) * [6.0, 3.0, 1.0]
    face = rng.integers(0, 3, size=n)
    pts[np.arange(n), face] = np.sign(pts[np.arange(n), face]) * np.array([6.0, 3.0, 1.0])[face]
    return pts.astype(np.float32)


def _reference_signature(aligned: np.ndarray) -> np.ndarray:
    """A literal float64 reading of M2DP.m / CountVote2D.c: atan2 and edge search."""
    az = np.linspace(-np.pi / 2, np.pi / 2, 4)
    el = np.linspace(0, np.pi / 2, 16)
    max_rho = np.sqrt(np.max(np.sum(aligned**2, axis=1)))
    t_edges = np.linspace(-np.pi, np.pi, 17)
    r_edges = np.linspace(0, np.sqrt(max_rho), 9) ** 2
    r_edges[-1] += 0.001
    rows = []
    for a in az:
        for e in el:
            n = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
            px = np.array([1.0, 0, 0]) - n[0] * n
            py = np.cross(n, px)
            x, y = aligned @ px, aligned @ py
            # first bin whose upper edge is strictly greater; overflow -> last bin
            it = np.searchsorted(t_edges[1:-1], np.arctan2(y, x), side="right")
            ir = np.searchsorted(r_edges[1:-1], np.hypot(x, y), side="right")
            rows.append(np.bincount(ir * 16 + it, minlength=128) / len(aligned))
    return np.array(rows)


# ---------------------------------------------------------------- small exact cases


def test_first_plane_axes_by_hand():
    # azimuth -90 deg, elevation 0: normal (0,-1,0), px = x axis, py = n x px = +z
    px, py = projection_planes(4, 16)
    assert px.shape == py.shape == (3, 64)
    np.testing.assert_allclose(px[:, 0], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(py[:, 0], [0, 0, 1], atol=1e-15)
    # elevation 90 deg: normal +z, px = x axis, py = z x x = +y, for every azimuth
    for k in (15, 31, 47, 63):
        np.testing.assert_allclose(px[:, k], [1, 0, 0], atol=1e-15)
        np.testing.assert_allclose(py[:, k], [0, 1, 0], atol=1e-15)
    # px is not normalised: azimuth -30 deg, elevation 0 -> |px| = sqrt(1 - cos^2 30) = 0.5
    assert np.linalg.norm(px[:, 16]) == pytest.approx(0.5)


def test_signature_bins_by_hand():
    # On the first plane a point (x, y, z) projects to (x, z). maxRho = |(2, 0, 0.2)|.
    pts = np.array([[2.0, 0.0, 0.2], [0.1, 0.0, -1.5], [-0.3, 0.0, 0.4], [0.05, 0.0, -0.01]])
    a = signature_matrix(pts, M2DPParams())
    assert a.shape == (64, 128)
    # (2, .2): theta 5.7 deg -> sector 8; rho = maxRho -> ring 7   -> 7*16+8  = 120
    # (.1, -1.5): theta -86.2 deg -> sector 4; 8*sqrt(1.503/2.01) = 6.9 -> 6*16+4 = 100
    # (-.3, .4): theta 126.9 deg -> sector 13; 8*sqrt(.5/2.01) = 3.99 -> 3*16+13 = 61
    # (.05, -.01): theta -11.3 deg -> sector 7; 8*sqrt(.051/2.01) = 1.27 -> 1*16+7 = 23
    expected = np.zeros(128)
    expected[[120, 100, 61, 23]] = 0.25
    np.testing.assert_array_equal(a[0], expected)
    np.testing.assert_allclose(a.sum(axis=1), 1.0)


def test_rank_one_signature_gives_its_factors():
    # A = a b^T has u1 = a/|a|, v1 = b/|b| (positive sign rule)
    rng = np.random.default_rng(3)
    a, b = rng.uniform(0.1, 1, 64), rng.uniform(0.1, 1, 128)
    d = descriptor_from_signature(np.outer(a, b))
    np.testing.assert_allclose(d[:64], a / np.linalg.norm(a), atol=1e-12)
    np.testing.assert_allclose(d[64:], b / np.linalg.norm(b), atol=1e-12)
    lapack = descriptor_from_signature(np.outer(a, b), svd_sign="lapack")
    assert np.allclose(lapack, d) or np.allclose(lapack, -d)


def test_pca_axes_follow_matlab_sign_convention():
    # Corners of a 12 x 6 x 2 box have principal axes x, y, z exactly. Turned
    # 120 deg about z they become a1 = (-.5, .866, 0) (largest entry +, kept)
    # and R e_y = (-.866, -.5, 0) (largest entry -, so flipped to (.866, .5, 0)):
    # the aligned frame is then a mirror image (det -1), as MATLAB's pca gives.
    corners = np.array([[x, y, z] for x in (-6, 6) for y in (-3, 3) for z in (-1, 1)], float)
    c, s = np.cos(np.deg2rad(120)), np.sin(np.deg2rad(120))
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    turned = corners @ rot.T + [5.0, -2.0, 1.0]
    aligned = pca_align(turned)
    centred = turned - turned.mean(axis=0)
    np.testing.assert_allclose(aligned[:, 0], centred @ [c, s, 0], atol=1e-9)
    np.testing.assert_allclose(aligned[:, 1], centred @ [s, -c, 0], atol=1e-9)
    np.testing.assert_allclose(aligned[:, 2], centred @ [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(aligned[:, :2], corners[:, :2] * [1, -1], atol=1e-9)


# ---------------------------------------------------------------- properties


def test_norm_translation_and_permutation_on_synthetic():
    desc = M2DP()
    pts = _box_cloud()
    d = desc.compute(pts)
    assert d.shape == (192,) and d.dtype == np.float64
    assert np.linalg.norm(d) == pytest.approx(np.sqrt(2), abs=1e-12)
    assert (d >= 0).all()  # non-negative signature, positive sign rule
    shifted = desc.compute(pts.astype(np.float64) + [250.0, -40.0, 7.0])
    assert desc.distance(d, shifted)[0] < 1e-9
    perm = np.random.default_rng(0).permutation(len(pts))
    assert desc.distance(d, desc.compute(pts[perm]))[0] < 1e-9


def test_batched_forms_agree_bitwise(monkeypatch):
    desc = M2DP()
    rng = np.random.default_rng(11)
    queries = rng.normal(size=(7, 192))
    db = rng.normal(size=(13, 192))
    single = np.array([[desc.distance(q, m)[0] for m in db] for q in queries])
    rows = np.array([desc.distances(q, db)[0] for q in queries])
    monkeypatch.setattr(vector_common, "BLOCK_BYTES", 3 * 13 * 192 * 8)  # blocks of 3 queries
    pair, yaws = desc.pairwise(queries, db)
    assert np.array_equal(single, rows) and np.array_equal(single, pair)
    assert np.isnan(yaws).all() and np.isnan(desc.distance(queries[0], db[0])[1])
    assert desc.symmetric
    assert np.array_equal(single.T, desc.pairwise(db, queries)[0])
    assert desc.distances(queries[0], db[:0])[0].shape == (0,)


def test_bad_input_and_params():
    with pytest.raises(LirisError):
        M2DP().compute(np.zeros((10, 2), np.float32))
    with pytest.raises(LirisError):
        M2DP().compute(np.zeros((2, 3), np.float32))
    with pytest.raises(LirisError):
        M2DP().compute(np.ones((10, 3), np.float32))  # all identical
    with pytest.raises(LirisError):
        M2DP(M2DPParams(svd_sign="maybe"))
    with pytest.raises(LirisError):
        M2DP(M2DPParams(radial_bins=0))
    pts = _box_cloud(500)
    bad = pts.copy()
    bad[3] = np.nan
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        d = M2DP().compute(bad)
    assert any(issubclass(w.category, LirisWarning) for w in caught)
    assert M2DP().distance(d, M2DP().compute(np.delete(pts, 3, axis=0)))[0] < 1e-9


def test_presets_load():
    for preset in ("paper", "reference"):
        desc = get_descriptor("m2dp", preset=preset)
        assert isinstance(desc, M2DP) and desc.params == M2DPParams()


# ---------------------------------------------------------------- real KITTI scans


@pytest.fixture(scope="module")
def kitti():
    if not (SAMPLES / "velodyne" / "000094.bin").is_file():
        pytest.skip(f"real scans not found under {SAMPLES}")

    def load(frame: str) -> np.ndarray:
        raw = np.fromfile(SAMPLES / "velodyne" / f"{int(frame):06d}.bin", dtype=np.float32)
        return raw.reshape(-1, 4)[:, :3]

    scans = {f: load(f) for f in ("94", "95", "198", "199")}
    scans["r90"] = _rotate_z(scans["94"], 90)
    scans["r180"] = _rotate_z(scans["94"], 180)
    scans["r33"] = _rotate_z(scans["94"], 33)
    desc = M2DP()
    return scans, {k: desc.compute(v) for k, v in scans.items()}


def test_reference_distances_on_real_scans(kitti):
    _, d = kitti
    desc = M2DP()
    for (a, b), expected in REFERENCE.items():
        assert desc.distance(d[a], d[b])[0] == pytest.approx(expected, abs=6e-5), (a, b)
    for key in d:
        assert np.linalg.norm(d[key]) == pytest.approx(np.sqrt(2), abs=1e-12)


def test_neighbours_closer_than_other_place(kitti):
    _, d = kitti
    desc = M2DP()
    assert desc.distance(d["94"], d["95"])[0] < desc.distance(d["94"], d["198"])[0]
    assert desc.distance(d["198"], d["199"])[0] < desc.distance(d["95"], d["199"])[0]


def test_rotation_weakness_is_expected_behaviour(kitti):
    """Documented failure: a 90 or 180 degree yaw flips PCA axes (see m2dp.py).

    The same place turned around looks farther than an unrelated place, as in
    the authors' code; a 33 degree turn flips no axis and is matched exactly.
    """
    _, d = kitti
    desc = M2DP()
    other_place = desc.distance(d["94"], d["198"])[0]
    assert desc.distance(d["94"], d["r90"])[0] > other_place
    assert desc.distance(d["94"], d["r180"])[0] > 2 * other_place
    assert desc.distance(d["94"], d["r33"])[0] < 1e-4


def test_invariances_on_real_scan(kitti):
    scans, d = kitti
    desc = M2DP()
    pts = scans["94"]
    moved = pts.astype(np.float64) + [312.5, -87.25, 4.0]
    assert desc.distance(d["94"], desc.compute(moved))[0] < 1e-6
    perm = np.random.default_rng(5).permutation(len(pts))
    assert desc.distance(d["94"], desc.compute(pts[perm]))[0] < 1e-6


def test_float32_fast_path_matches_literal_float64(kitti):
    scans, _ = kitti
    for key in ("94", "198"):
        aligned = pca_align(scans[key])
        slow = _reference_signature(aligned)
        # both float32 routes: atan2 (the previous one) and fast (comparisons, the default)
        for fast in (signature_matrix(aligned, M2DPParams()),
                     signature_matrix_fast(scans[key], M2DPParams())):
            moved_points = np.abs(fast - slow).sum() * len(aligned) / 2
            assert moved_points <= 5  # of 64 x ~120k point-plane votes
            d_fast = descriptor_from_signature(fast)
            d_slow = descriptor_from_signature(slow)
            assert np.linalg.norm(d_fast - d_slow) < 1e-5
