"""Peers' conventions: per-query windows (frames, seconds), the band, and known counts."""

from __future__ import annotations

import numpy as np
import pytest
from test_protocols import ToyHist

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.conventions import (
    PRESETS,
    database_limits,
    get_convention,
    revisit_queries_within,
    with_overrides,
)
from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth, gt_coordinates
from lidar_iris_eval.evaluation.protocol1 import band_curve, protocol1
from lidar_iris_eval.matching.blocks import best_matches


def test_frame_window_limits_and_scan_context_skips_the_last_frame():
    liris = with_overrides(get_convention("liris"), exclude=3)
    assert database_limits(6, liris).tolist() == [-1, -1, -1, 0, 1, 2]
    sc = with_overrides(get_convention("scancontext-eval"), exclude=3)
    assert database_limits(6, sc).tolist() == [-1, -1, -1, 0, 1, -1]
    assert get_convention("scancontext-eval").exclude == 49


def test_time_windows_by_hand():
    times = np.arange(8, dtype=float)  # 1 s apart
    liris = with_overrides(get_convention("liris"), exclude_seconds=2.5)
    # t_j <= t_i - 2.5  ->  j <= i - 3
    assert database_limits(8, liris, times).tolist() == [-1, -1, -1, 0, 1, 2, 3, 4]
    logg3d = with_overrides(get_convention("logg3d"), exclude_seconds=2.5)
    # queries once 2.5 s passed (i >= 3); database up to the first scan after t_i - 2.5 (i - 2)
    assert database_limits(8, logg3d, times).tolist() == [-1, -1, -1, 1, 2, 3, 4, 5]
    with pytest.raises(LirisError, match="scan times"):
        database_limits(8, logg3d, None)
    with pytest.raises(LirisError, match="non-decreasing"):
        database_limits(3, logg3d, np.array([0.0, 2.0, 1.0]))


def test_mapclosures_is_refused_with_the_reason():
    with pytest.raises(LirisError, match="point clouds|scans"):
        get_convention("mapclosures")
    with pytest.raises(LirisError, match="choose from"):
        get_convention("nope")


@pytest.mark.parametrize("budget", [1, 100, 1 << 20])
def test_per_query_search_equals_the_frame_window_search(budget):
    rng = np.random.default_rng(3)
    desc = ToyHist()
    descs = rng.random((40, 16))
    descs[7] = np.nan  # NaN distances never win
    ref = best_matches(desc, descs, 5, budget)
    conv = with_overrides(get_convention("liris"), exclude=5)
    got = best_matches(desc, descs, database_limits(40, conv), budget)  # per-query limits
    np.testing.assert_array_equal(got.query, ref.query)
    np.testing.assert_array_equal(got.match, ref.match)
    np.testing.assert_array_equal(got.distance, ref.distance)


def test_standard_convention_equals_protocol1():
    rng = np.random.default_rng(5)
    n = 60
    t = np.linspace(0, 2 * np.pi, n)
    positions = np.stack([20 * np.cos(t), np.zeros(n), 20 * np.sin(t)], 1)  # closes on itself
    descs = rng.random((n, 8)) + positions[:, :1] * 0.01
    desc = ToyHist()
    conv = with_overrides(get_convention("liris"), exclude=5, radius=6.0)
    ref = protocol1(desc, descs, positions, exclude=5, radius=6.0)
    got = protocol1(desc, descs, positions, conv)
    assert got.metrics == ref.metrics
    np.testing.assert_array_equal(got.curve.recall, ref.curve.recall)


def test_band_predictions_are_neither_true_nor_false():
    # 4 queries, all revisits; distances 1..4; q0 true, q1 band, q2 false, q3 true
    dist = np.array([1.0, 2.0, 3.0, 4.0])
    true = np.array([True, False, False, True])
    band = np.array([False, True, False, False])
    revisit = np.ones(4, bool)
    curve = band_curve(dist, true, band, revisit, 4, "accepted")
    # at tau=1: TP 1, FP 0, denominator 4 -> R 1/4; tau=3: q1 accepted in band leaves the
    # denominator, q2 accepted wrong too -> TP 1, FP 1, denominator 2; tau=4: TP 2, denom 2
    assert curve.threshold.tolist() == [1.0, 3.0, 4.0]
    assert curve.precision.tolist() == [1.0, 0.5, 2 / 3]
    assert curve.recall.tolist() == [0.25, 0.5, 1.0]


def kitti_positions(kitti_dir):
    poses = np.loadtxt(kitti_dir / "poses" / "00.txt")
    return poses[:, [3, 7, 11]]


def count_revisits(positions, conv, times=None):
    limits = database_limits(len(positions), conv, times)
    coords = gt_coordinates(positions, conv.pose_frame, conv.distance)
    return int(revisit_queries_within(coords, limits, conv.radius, conv.inclusive_radius).sum())


def test_kitti00_counts_under_the_presets(kitti_dir):
    positions = kitti_positions(kitti_dir)
    # liris: the README's 816 (E = 30), also what compute_ground_truth gives
    assert count_revisits(positions, PRESETS["liris"]) == 816
    assert compute_ground_truth(positions, 4.0, 30).n_revisits == 816
    # Scan Context's fast_evaluator rules (5 m planar, E = 49, last frame not a query)
    assert count_revisits(positions, PRESETS["scancontext-eval"]) == 803
    # the same rules at 4 m give the 790 loops quoted for KITTI 00 (irapkaist/scancontext#12)
    assert count_revisits(positions, with_overrides(PRESETS["scancontext-eval"], radius=4.0)) \
        == 790


def test_gt_convention_on_kitti00_poses(kitti_dir, capsys):
    import json

    from conftest import run_cli

    poses = kitti_dir / "poses" / "00.txt"
    code, out, err = run_cli(["gt", "--poses", poses, "--convention", "scancontext-eval",
                              "--json"], capsys)
    assert code == 0, err
    summary = json.loads(out)
    assert summary["convention"] == "scancontext-eval"
    assert (summary["radius_m"], summary["distance"]) == (5.0, "planar")
    assert summary["revisit_queries"] == 803 and summary["queries"] == 4541 - 49 - 1
    # an explicit option wins over the preset and renames it
    code, out, _ = run_cli(["gt", "--poses", poses, "--convention", "scancontext-eval",
                            "--radius", "4", "--json"], capsys)
    summary = json.loads(out)
    assert summary["convention"] == "scancontext-eval+custom"
    assert summary["revisit_queries"] == 790


def test_gt_convention_errors(tmp_path, capsys):
    from conftest import assert_one_line_error, run_cli

    poses = tmp_path / "p.txt"
    np.savetxt(poses, np.tile(np.eye(4)[:3].ravel(), (5, 1)))
    code, _, err = run_cli(["gt", "--poses", poses, "--convention", "mapclosures"], capsys)
    assert_one_line_error(code, err, "--convention mapclosures", "poses alone")
    code, _, err = run_cli(["gt", "--poses", poses, "--convention", "logg3d"], capsys)
    assert_one_line_error(code, err, "needs scan times")
