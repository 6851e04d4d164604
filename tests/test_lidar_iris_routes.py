"""The fast LiDAR Iris kernel against the baseline route (the previous kernel, kept verbatim).

Both routes must give bitwise-equal distances and shifts for every shift
search and match mode, on simulated full-resolution scans and on the shared
real KITTI scans with rotated and translated copies. The band-peak ranking,
whose one-pass form replaces repeated scans, is also checked on surfaces with
exactly tied maxima, where the order of ties decides the result.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.lidar_iris import compare_blocks, kernels, kernels_baseline
from lidar_iris_eval.descriptors.lidar_iris import descriptor as li
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate import build_scenario, resolve_config
from lidar_iris_eval.simulate.sensors import simulate_scan

_HERE = Path(__file__).resolve()
#: ../shared next to the repository (or next to the folder of git worktrees)
_SHARED = next(
    (p / "shared" for p in _HERE.parents[2:4] if (p / "shared" / "data").is_dir()), None
)
VELODYNE = None if _SHARED is None else _SHARED / "data" / "kitti" / "samples" / "00" / "velodyne"

SEARCHES = ("phase", "phase+refine", "exhaustive")
MODES = ("same", "reverse", "both")


def _turn(points: np.ndarray, degrees: float, dx: float = 0.0, dy: float = 0.0) -> np.ndarray:
    t = np.radians(degrees)
    c, s = np.cos(t), np.sin(t)
    p = points[:, :3].astype(np.float64)
    return np.c_[c * p[:, 0] - s * p[:, 1] + dx, s * p[:, 0] + c * p[:, 1] + dy,
                 p[:, 2]].astype(np.float32)


def _assert_routes_equal(descs: np.ndarray, params) -> None:
    fast_d, fast_s = compare_blocks(descs, descs, params, route="fast")
    base_d, base_s = compare_blocks(descs, descs, params, route="baseline")
    assert np.array_equal(fast_d, base_d, equal_nan=True)
    assert np.array_equal(fast_s, base_s)
    assert np.isfinite(fast_d).mean() > 0.9  # the case is not vacuous


@pytest.fixture(scope="module")
def simulated() -> np.ndarray:
    """Full-resolution hdl64 scans (2048 azimuth steps) of the simulated town, any yaw."""
    cfg = resolve_config("tiny-mixed", dict(sensor="hdl64", azimuth_steps=2048))
    scen = build_scenario(cfg)
    rng = np.random.default_rng(3)
    out = []
    for frame in np.linspace(0, len(scen.poses) - 1, 6).astype(int):
        for _ in range(2):
            pose = scen.poses[frame].copy()
            yaw = rng.uniform(0, 2 * np.pi)
            c, s = np.cos(yaw), np.sin(yaw)
            pose[:3, :3] = pose[:3, :3] @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
            pose[:2, 3] += rng.uniform(-1.5, 1.5, 2)
            scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(frame), pose, rng)
            out.append(scan.points)
    return out


@pytest.fixture(scope="module")
def real_scans() -> list[np.ndarray]:
    """The four shared KITTI scans and rotated, translated copies of them."""
    if VELODYNE is None or not VELODYNE.is_dir():
        pytest.skip("../shared KITTI sample scans are not available")
    scans = [np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3]
             for f in sorted(VELODYNE.glob("*.bin"))]
    out = []
    for i, scan in enumerate(scans):
        out.append(scan)
        for deg, dx in ((37.5, 0.0), (181.0, 1.2), (270.3, -0.7)):
            out.append(_turn(scan, deg + i, dx, 0.5 * dx))
    return out


@pytest.mark.parametrize("preset", ["paper", "reference"])
def test_routes_equal_on_simulated_scans(simulated, preset):
    base = get_descriptor("lidar-iris", preset=preset)
    descs = np.stack([base.compute(p) for p in simulated])
    for search in SEARCHES:
        for mode in MODES:
            params = dataclasses.replace(base.params, shift_search=search, match_mode=mode)
            _assert_routes_equal(descs, params)


@pytest.mark.parametrize("preset", ["paper", "reference"])
def test_routes_equal_on_real_scans_and_rotated_copies(real_scans, preset):
    base = get_descriptor("lidar-iris", preset=preset)
    descs = np.stack([base.compute(p) for p in real_scans])
    for search in SEARCHES:
        for mode in MODES:
            params = dataclasses.replace(base.params, shift_search=search, match_mode=mode)
            _assert_routes_equal(descs, params)
    # the rotated copies are found at their rotation by both routes (same place, ~0 error)
    d, s = compare_blocks(descs[:1], descs[1:2], base.params)
    assert abs(s[0, 0] - 37.5) <= 1.5


def test_serial_and_parallel_launches_equal(simulated, monkeypatch):
    """A few pairs go to ``pair_block_serial``: the same tiles and pair code as the
    parallel kernel, so the same bits whichever launch computed them."""
    base = get_descriptor("lidar-iris")
    descs = np.stack([base.compute(p) for p in simulated])
    for search in SEARCHES:
        for mode in MODES:
            params = dataclasses.replace(base.params, shift_search=search, match_mode=mode)
            monkeypatch.setattr(li, "PARALLEL_MIN_PAIRS", 0)
            par = compare_blocks(descs, descs, params)
            monkeypatch.setattr(li, "PARALLEL_MIN_PAIRS", 1 << 30)
            ser = compare_blocks(descs, descs, params)
            assert np.array_equal(par[0], ser[0], equal_nan=True)
            assert np.array_equal(par[1], ser[1])


@pytest.mark.parametrize("peaks", [1, 2, 3, 5])
def test_band_peaks_rank_exact_ties_like_the_baseline(peaks):
    """A single harmonic k gives k exactly equal maxima: ties go to the lower column."""
    n, nk = 360, 24
    desc = get_descriptor("lidar-iris")
    cos_t, sin_t = li._trig_tables(n, nk)
    cos_c, sin_c = np.ascontiguousarray(cos_t[:, ::3]), np.ascontiguousarray(sin_t[:, ::3])
    rng = np.random.default_rng(0)
    assert desc.params.refine_peaks == 2
    for k in (3, 4, 6):
        for phase in (0.0, 0.4, 1.1):
            br1 = np.zeros((4, nk), np.float32)
            bi1 = np.zeros((4, nk), np.float32)
            br1[:, k - 1] = np.float32(np.cos(phase))
            bi1[:, k - 1] = np.float32(np.sin(phase))
            br2 = br1.copy()
            bi2 = np.zeros_like(bi1)
            br2[:, k - 1] = 1.0
            for flip in (False, True):
                old = np.full(peaks, -7, np.int64)
                new = np.full(peaks, -7, np.int64)
                a = kernels_baseline._band_peaks(br1, bi1, br2, bi2, cos_t, sin_t, flip, peaks,
                                                 np.empty(nk), np.empty(nk), np.empty(n), old)
                b = kernels._band_peaks(br1, bi1, br2, bi2, cos_t, sin_t, cos_c, sin_c, flip,
                                        peaks, np.empty(nk), np.empty(nk), np.empty(n), new,
                                        np.empty(peaks * 5, np.int64), np.empty(peaks * 5))
                assert a == b == min(peaks, k)
                assert np.array_equal(old[:a], new[:b])
                # ties in column order: k equally spaced maxima, increasing
                assert np.all(np.diff(new[:b]) > 0)
    # random surfaces too (no ties): the same peaks
    for _ in range(50):
        br1, bi1, br2, bi2 = (rng.normal(size=(4, nk)).astype(np.float32) for _ in range(4))
        old = np.empty(peaks, np.int64)
        new = np.empty(peaks, np.int64)
        a = kernels_baseline._band_peaks(br1, bi1, br2, bi2, cos_t, sin_t, False, peaks,
                                         np.empty(nk), np.empty(nk), np.empty(n), old)
        b = kernels._band_peaks(br1, bi1, br2, bi2, cos_t, sin_t, cos_c, sin_c, False, peaks,
                                np.empty(nk), np.empty(nk), np.empty(n), new,
                                np.empty(peaks * 5, np.int64), np.empty(peaks * 5))
        assert a == b and np.array_equal(old[:a], new[:b])


def test_unknown_route_is_an_error():
    desc = get_descriptor("lidar-iris")
    d = desc.compute(np.random.default_rng(0).normal(size=(500, 3)).astype(np.float32) * 10)
    with pytest.raises(LirisError, match="route"):
        compare_blocks(d, d, desc.params, route="turbo")
