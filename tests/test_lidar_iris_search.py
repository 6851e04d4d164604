"""LiDAR Iris shift search against the exhaustive oracle, and reverse/both on real scans.

The oracle is ``shift_search: exhaustive`` (all 360 column shifts), itself
checked against the per-shift distance curve. Same-place scans come from the
simulator (os0-128 and vlp16 sensor presets: scans cast at poses up to 2 m
and any yaw apart) and from rotated and translated copies of the shared real
KITTI scans.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.lidar_iris import distance_curve, reference_loop
from lidar_iris_eval.simulate import build_scenario, resolve_config
from lidar_iris_eval.simulate.sensors import simulate_scan

VELODYNE = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "samples" / "00"
VELODYNE = VELODYNE / "velodyne"


def rotate_translate(points: np.ndarray, degrees: float, dx: float = 0.0, dy: float = 0.0):
    """Rotate counter-clockwise about +z by ``degrees``, then translate (float64 maths)."""
    t = np.radians(degrees)
    c, s = np.cos(t), np.sin(t)
    p = points[:, :3].astype(np.float64)
    x = c * p[:, 0] - s * p[:, 1] + dx
    y = s * p[:, 0] + c * p[:, 1] + dy
    return np.c_[x, y, p[:, 2]].astype(np.float32)


def same_place_scans(sensor: str, places: int = 8, views: int = 4, seed: int = 5):
    """Scans of the simulated town: ``views`` poses per place, up to 2 m and any yaw apart.

    Returns a list of ``(place, points)``.
    """
    cfg = resolve_config("tiny-mixed", dict(sensor=sensor, azimuth_steps=360))
    scen = build_scenario(cfg)
    rng = np.random.default_rng(seed)
    frames = np.linspace(0, len(scen.poses) - 1, places).astype(int)
    out = []
    for place, frame in enumerate(frames):
        for _ in range(views):
            pose = scen.poses[frame].copy()
            yaw = rng.uniform(0, 2 * np.pi)
            c, s = np.cos(yaw), np.sin(yaw)
            turn = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
            pose[:3, :3] = pose[:3, :3] @ turn
            pose[:2, 3] += rng.uniform(-1.4, 1.4, 2)
            scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(frame), pose, rng)
            out.append((place, scan.points))
    return out


def found_rate(desc, scans) -> tuple[float, float, int]:
    """(share of same-place pairs at the exhaustive-best distance, share within 0.01, pairs)."""
    oracle = get_descriptor("lidar-iris", shift_search="exhaustive", **_overrides(desc))
    descs = np.stack([desc.compute(p) for _, p in scans])
    places = np.array([place for place, _ in scans])
    d, _ = desc.pairwise(descs, descs)
    best, _ = oracle.pairwise(descs, descs)
    pairs = (places[:, None] == places[None, :]) & ~np.eye(len(scans), dtype=bool)
    excess = d[pairs] - best[pairs]
    assert np.all(excess >= 0)  # the oracle is never beaten
    return float(np.mean(excess <= 0)), float(np.mean(excess <= 0.01)), int(pairs.sum())


def _overrides(desc) -> dict:
    p = desc.params
    return dict(z_low=p.z_low, z_high=p.z_high)


def test_exhaustive_is_the_minimum_of_the_distance_curve_and_the_reference_loop():
    scans = same_place_scans("vlp16", places=2, views=3)
    desc = get_descriptor("lidar-iris", shift_search="exhaustive")
    p = desc.params
    descs = [desc.compute(pts) for _, pts in scans]
    for i, j in [(0, 1), (0, 4), (5, 2)]:
        curve = distance_curve(descs[i], descs[j], p)
        d, yaw = desc.distance(descs[i], descs[j])
        assert d == np.nanmin(curve) and yaw == float(np.nanargmin(curve))
        prep = [reference_loop.prepare(x, p) for x in (descs[i], descs[j])]
        assert reference_loop.reference_distance(*prep, p) == (d, int(yaw))


@pytest.mark.parametrize("sensor", ["vlp16", "os0-128"])
def test_refined_search_reaches_the_exhaustive_best_in_simulation(sensor):
    """The issue's bar: >= 99 % of same-place pairs at the exhaustive best (measured
    on these 96 pairs: 100 % for both sensors; the old +-2 window around the
    phase peak: vlp16 100 %, os0-128 67 %)."""
    scans = same_place_scans(sensor)
    desc = get_descriptor("lidar-iris", sensor=sensor)
    exact, close, n = found_rate(desc, scans)
    assert n == 8 * 4 * 3
    assert exact >= 0.99 and close >= 0.99, (exact, close)
    phase = get_descriptor("lidar-iris", sensor=sensor, shift_search="phase")
    old_exact, _, _ = found_rate(phase, scans)
    assert old_exact <= exact, (old_exact, exact)


@pytest.fixture(scope="module")
def kitti_scans():
    if not VELODYNE.is_dir():
        pytest.skip("../shared KITTI sample scans are not available")
    return {
        n: np.fromfile(VELODYNE / f"{n:06d}.bin", dtype=np.float32).reshape(-1, 4)[:, :3]
        for n in (94, 95, 198, 199)
    }


def test_refined_search_on_rotated_and_translated_real_scans(kitti_scans):
    """Copies of each real scan turned by any yaw and moved up to 3 m, plus the real
    neighbour pairs (94/95, 198/199): every pair reaches the exhaustive best."""
    rng = np.random.default_rng(3)
    scans = []
    for place, n in enumerate((94, 198)):
        scans.append((place, kitti_scans[n]))
        scans.append((place, kitti_scans[n + 1]))
        for _ in range(4):
            dx, dy = rng.uniform(-2.1, 2.1, 2)
            scans.append((place, rotate_translate(kitti_scans[n], rng.uniform(0, 360), dx, dy)))
    exact, close, n = found_rate(get_descriptor("lidar-iris"), scans)
    assert n == 2 * 6 * 5
    assert exact == 1.0, exact


# Authors' C++ (ALGORITHMS.md, reference outputs; matchNum 1 gives the matchNum 0
# numbers on these pairs): scan 94 against itself rotated by N degrees
ROTATED = [(17, 0.0011), (90, 0.0021), (180, 0.0007), (263, 0.0010)]


@pytest.mark.parametrize("mode", ["reverse", "both"])
def test_reverse_and_both_find_rotated_copies_like_the_authors(kitti_scans, mode):
    """The bar: within 0.005 of the C++ distance and 2 degrees of its yaw (we get 1e-3, 0)."""
    desc = get_descriptor("lidar-iris", preset="reference", match_mode=mode)
    base = desc.compute(kitti_scans[94])
    for degrees, d_ref in ROTATED:
        d, yaw = desc.distance(base, desc.compute(rotate_translate(kitti_scans[94], degrees)))
        assert abs(d - d_ref) < 1e-3, (degrees, d, d_ref)
        assert yaw == degrees, (degrees, yaw)
    # a reverse revisit: the same place seen after a U-turn (turned 180 deg, moved 1.5 m)
    d, yaw = desc.distance(base, desc.compute(rotate_translate(kitti_scans[94], 180, 1.5, 0)))
    assert d < 0.3 and abs(yaw - 180) <= 2, (d, yaw)  # unrelated places: > 0.4


def simulated_sequence(sensor: str, every: int = 2, seed: int = 0):
    """Scans and LiDAR positions of the tiny-mixed town (same and reverse revisits, up
    to 3 m lateral offset) with ``sensor``, at 360 azimuth steps, every 2nd frame."""
    scen = build_scenario(resolve_config("tiny-mixed", dict(sensor=sensor, azimuth_steps=360)))
    rng = np.random.default_rng(seed)
    frames = range(0, len(scen.poses), every)
    scans = [
        simulate_scan(scen.sensor, scen.world.ground, scen.primitives(f), scen.poses[f], rng).points
        for f in frames
    ]
    return scans, np.array([scen.poses[f][:3, 3] for f in frames])


@pytest.mark.parametrize("sensor", ["vlp16", "os0-128"])
def test_every_recognisable_pair_under_4m_of_a_sequence_reaches_the_exhaustive_best(sensor):
    """The issue's bar on a whole simulated sequence: every pair < 4 m apart whose
    best distance beats 99 % of unrelated places (> 15 m apart) is searched to the
    exhaustive best on >= 99 % of pairs. The old phase window fails this (83-85 %
    measured at 1024 azimuth steps), so the test can fail. Weak pairs (best no better
    than unrelated places: flat curves) are only required to be close on average."""
    from lidar_iris_eval.descriptors.lidar_iris.oracle import search_agreement

    scans, positions = simulated_sequence(sensor)
    desc = get_descriptor("lidar-iris", sensor=sensor)
    descs = np.stack([desc.compute(p) for p in scans])
    res = search_agreement(desc, descs, positions)
    rec = res.recognisable
    assert np.all(res.excess >= 0)  # the oracle is never beaten
    assert rec.sum() >= 300 and res.unrelated.size == 2000, (rec.sum(), res.unrelated.size)
    assert res.rate(rec) >= 0.99, res.rate(rec)
    assert res.rate(~rec, tolerance=0.01) >= 0.9, res.rate(~rec, tolerance=0.01)
    phase = get_descriptor("lidar-iris", sensor=sensor, shift_search="phase")
    old = search_agreement(phase, descs, positions)
    assert old.rate(rec) < res.rate(rec), (old.rate(rec), res.rate(rec))
