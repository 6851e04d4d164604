"""Issue 22: the five convention repros and the ignored ``shift_window``, on ``tiny-mixed``.

Each test states the defect it pins (as reported in the issue) and checks
the behaviour with expectations derived independently of the code under test
(the preset's own numbers, the run's own conventions, a null for an
undefined metric).
"""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from tests.conftest import run_cli

pytest.importorskip("lidar_iris_eval.simulate")


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """``liris simulate sim --world tiny-mixed`` (220 scans at 10 Hz, 22 s)."""
    from lidar_iris_eval.simulate import simulate_sequence

    root = tmp_path_factory.mktemp("arch")
    simulate_sequence(root / "sim", "tiny-mixed")
    return root


def _eval(root, capsys, name, *args):
    out = root / name
    code, stdout, err = run_cli(["eval", root / "sim", "--out", out, "--overwrite", "-q",
                                 "--cache-dir", root / "cache", "--json", *args], capsys)
    assert code == 0, err
    return out, json.loads(stdout), err


def _row(metrics, protocol, name):
    return next(r for r in metrics["results"] if r["protocol"] == protocol
                and r["descriptor"] == name)


def test_repro1_logg3d_run_reads_back_and_plots(sim, capsys):
    """Repro 1: ``--convention logg3d`` then ``liris plot`` failed on ``int(None)``;
    the reader must rebuild the convention's own ground truth (3 m, 30 s)."""
    from lidar_iris_eval.evaluation.conventions import get_convention
    from lidar_iris_eval.runs.reader import load_run

    run_dir, metrics, _ = _eval(sim, capsys, "r1", "--protocol", "1", "--protocol", "2",
                                "-d", "scan-context", "--convention", "logg3d")
    run = load_run(run_dir)
    conv = get_convention("logg3d")
    assert run.gt_settings().radius == conv.radius == 3.0
    assert run.gt_settings().exclude_seconds == 30.0
    gt = run.ground_truth()
    # 220 scans at 10 Hz span 21.9 s < 30 s: no scan is a query under LoGG3D's rule
    assert gt.radius == 3.0 and gt.n_revisits == 0
    assert _row(metrics, 1, "scan-context")["n_queries"] == 0
    code, _, err = run_cli(["plot", run_dir, "--out", sim / "fig1"], capsys)
    assert code == 0, err


def test_repro2_two_stage_under_convention(sim, capsys):
    """Repro 2: gosmatch under ``--convention scancontext-eval`` raised a TypeError
    (ragged features through ``pairwise``); it must go through retrieval + verification."""
    _, metrics, err = _eval(sim, capsys, "r2", "--protocol", "1", "-d", "gosmatch",
                            "--convention", "scancontext-eval")
    assert "Traceback" not in err
    row = _row(metrics, 1, "gosmatch")
    assert row["match_source"].startswith("two-stage:")
    # E = 49 and the last frame is never a query: 220 - 49 - 1 queries
    assert row["n_queries"] == 220 - 49 - 1
    assert row["pose_estimate"] == "full"


def test_repro3_pose_errors_kept_under_convention(sim, capsys):
    """Repro 3: scan-context under a peer convention dropped its (yaw) pose estimate."""
    _, standard, _ = _eval(sim, capsys, "r3a", "--protocol", "1", "-d", "scan-context")
    _, peer, _ = _eval(sim, capsys, "r3b", "--protocol", "1", "-d", "scan-context",
                       "--convention", "scancontext-eval")
    assert _row(standard, 1, "scan-context")["pose_estimate"] == "yaw"
    row = _row(peer, 1, "scan-context")
    assert row["pose_estimate"] == "yaw"
    assert "rre_deg_median" in row


def test_repro4_no_queries_is_null_not_zero(sim, capsys):
    """Repro 4: protocol 1 with ``n_queries: 0`` under logg3d wrote 0.0 for AP, F1, R@100P."""
    _, metrics, _ = _eval(sim, capsys, "r4", "--protocol", "1", "-d", "scan-context",
                          "--convention", "logg3d")
    row = _row(metrics, 1, "scan-context")
    assert row["n_queries"] == 0
    for key in ("ap", "f1_max", "r100p"):
        assert row[key] is None, (key, row[key])


def test_repro5_recorded_conventions_are_the_ones_scored(sim):
    """Repro 5: ``evaluate(..., Settings(), convention=scancontext-eval)`` scored with
    5 m / planar / E = 49 but recorded 4 m / 3-D / E = 30."""
    from lidar_iris_eval.evaluation.conventions import get_convention
    from lidar_iris_eval.evaluation.evaluate import Settings, evaluate

    conv = get_convention("scancontext-eval")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = evaluate(sim / "sim", ["scan-context"], protocols=(1,), settings=Settings(),
                       convention=conv, cache=sim / "cache")
    recorded = run.header()["conventions"]
    assert recorded["radius"] == 5.0
    assert recorded["distance"] == "planar"
    assert recorded["exclude"] == 49
    gt = run.results[0].protocol1.gt
    assert (gt.radius, gt.distance) == (5.0, "planar")
    assert run.rows[0]["n_queries"] == 220 - 49 - 1


def test_shift_window_ignored_by_default_search_warns(sim, capsys):
    """Real-data finding: ``shift_window`` under the default search changed nothing, silently."""
    from lidar_iris_eval.errors import LirisWarning

    code, _, err = run_cli(["extract", sim / "sim", "-d", "lidar-iris", "-q",
                            "--cache-dir", sim / "cache", "--param",
                            "lidar-iris.shift_window=180"], capsys)
    assert code == 0, err
    assert "shift_window" in err and "ignored" in err
    from lidar_iris_eval.descriptors import get_descriptor

    with pytest.warns(LirisWarning, match="shift_window"):
        get_descriptor("lidar-iris", shift_window=180)
    with warnings.catch_warnings():  # the search that uses it: no warning
        warnings.simplefilter("error", LirisWarning)
        get_descriptor("lidar-iris", shift_window=180, shift_search="phase")


def test_no_yaw_means_every_rotation_entry_is_empty():
    """Real-data finding: M2DP/ESF rows wrote T02, T12, T20, T21 as 0.0 (the doc says empty)."""
    from lidar_iris_eval.descriptors.base import yaw_to_pose

    T = yaw_to_pose(np.array([np.nan, 90.0]))
    assert np.isnan(T[0, :3, :]).all()
    np.testing.assert_allclose(T[1, :3, :3], [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-12)
    assert np.isnan(T[1, :3, 3]).all() and T[1, 3, 3] == 1.0
