"""Issue 23 end to end: ``liris eval --refine gicp --gt-pose refined --export-loops``."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from conftest import assert_one_line_error, run_cli

pytest.importorskip("small_gicp")

from lidar_iris_eval.evaluation.loop_export import read_g2o  # noqa: E402


@pytest.fixture(scope="module")
def refined_run(tmp_path_factory):
    """tiny-mixed at a coarse azimuth (fast), two yaw-only methods refined."""
    from lidar_iris_eval.cli import main
    from lidar_iris_eval.simulate import simulate_sequence

    root = tmp_path_factory.mktemp("loop-poses")
    seq = simulate_sequence(root / "seq", preset="tiny-mixed", azimuth_steps=256)
    run = root / "run"
    main(["eval", str(seq), "--protocol", "1", "-d", "lidar-iris,scan-context",
          "--refine", "gicp", "--gt-pose", "refined", "--export-loops", str(root / "loops.g2o"),
          "--cache-dir", str(root / "cache"), "--out", str(run), "--quiet"])
    metrics = json.loads((run / "metrics.json").read_text())
    return root, seq, run, {r["descriptor"]: r for r in metrics["results"]}, metrics


def test_yaw_only_methods_export_refined_g2o_edges(refined_run):
    root, seq, run, rows, _ = refined_run
    n_frames = len(list((seq / "velodyne").glob("*.bin")))
    for name in ("lidar-iris", "scan-context"):
        table = pd.read_csv(run / "protocol1" / name / "matches.csv")
        tau = rows[name]["f1_threshold"]
        accepted = int(((table["match"] >= 0) & (table["distance"] <= tau)).sum())
        graph = read_g2o(root / f"loops-{name}.g2o")
        assert len(graph.vertices) == n_frames
        assert len(graph.edges) == accepted > 50
        infos = np.array([np.diag(info) for *_, info in graph.edges])
        assert (infos != 1.0).all()  # fitness-derived, not the placeholder


def test_refined_pose_bar_and_matches_columns(refined_run):
    _, _, run, rows, _ = refined_run
    for name in ("lidar-iris", "scan-context"):
        row = rows[name]
        assert row["pose_estimate"] == "yaw"
        assert row["rr_kind"] == "rotation-only" and row["rr"] is not None
        assert row["refined_rr_kind"] == "full"
        assert row["refined_rte_m_median"] < 0.2 and row["refined_rre_deg_median"] < 1.0
        assert row["refined_rr"] > 0.9
        assert row["registration_ms_per_loop"] > 0 and row["registration_prepare_ms_per_scan"] > 0
        table = pd.read_csv(run / "protocol1" / name / "matches.csv")
        # the method's pose is kept (yaw-only: no translation) beside the refined one
        assert table.loc[table["match"] >= 0, "T03"].isna().all()
        assert table.loc[table["match"] >= 0, "refined_T03"].notna().all()
        for col in ("inlier_ratio", "rmse_m", "registration_s", "refined_rte_m"):
            assert col in table


def test_gt_refined_changes_simulated_errors_little(refined_run):
    _, _, _, rows, metrics = refined_run
    assert metrics["conventions"]["gt_pose"] == "refined"
    for row in rows.values():
        assert row["n_gt_refined"] > 50
        assert row["gt_refinement_m_median"] < 0.02
        # both figures reported; exact simulated ground truth: they differ by < 0.02 m
        assert abs(row["refined_rte_m_median"] - row["refined_rte_m_median_refined_gt"]) < 0.02


def test_show_prints_the_loop_table(refined_run, capsys):
    _, _, run, _, _ = refined_run
    code, out, err = run_cli(["show", run], capsys)
    assert code == 0, err
    assert "refined_rr" in out and "register_ms_per_loop" in out and "rotation-only" in out
    code, out, _ = run_cli(["show", run, "--no-conventions"], capsys)
    assert "rotation-only" not in out  # the metrics table only


def test_acceptance_rule_rejects_and_is_named(refined_run, tmp_path, capsys):
    root, seq, _, _, _ = refined_run
    code, out, err = run_cli(["eval", seq, "--protocol", "1", "-d", "scan-context",
                              "--refine", "gicp", "--min-inlier-ratio", "0.99",
                              "--cache-dir", root / "cache", "--out", tmp_path / "r", "-q",
                              "--json"], capsys)
    assert code == 0, err
    row = json.loads(out)["results"][0]
    assert json.loads(out)["conventions"]["acceptance_rule"] == "inlier_ratio >= 0.99"
    table = pd.read_csv(tmp_path / "r" / "protocol1" / "scan-context" / "matches.csv")
    rejected = table["registration_accepted"] == 0
    assert row["n_rejected_by_registration"] == int((rejected & (table["match"] >= 0)).sum()) > 0
    assert np.isinf(table.loc[rejected, "distance"]).all()  # never predicted
    assert table.loc[rejected, "descriptor_distance"].notna().all()


def test_bad_flags_are_one_line(refined_run, tmp_path, capsys):
    _, seq, _, _, _ = refined_run
    base = ["eval", seq, "--protocol", "1", "-d", "scan-context", "--out", tmp_path / "r", "-q"]
    code, _, err = run_cli([*base, "--min-inlier-ratio", "0.5"], capsys)
    assert_one_line_error(code, err, "--min-inlier-ratio", "needs --refine")
    code, _, err = run_cli([*base, "--rr-thresholds", "2"], capsys)
    assert_one_line_error(code, err, "--rr-thresholds", "METRES,DEGREES")
    code, _, err = run_cli([*base, "--export-loops", tmp_path / "l.csv"], capsys)
    assert_one_line_error(code, err, "--export-loops", ".tum")


def test_objects_layout_says_n_a_in_one_line(tmp_path, capsys):
    from test_gosmatch_pipeline import _object_world

    seq, _ = _object_world(tmp_path / "objects")
    code, out, err = run_cli(["eval", seq, "-d", "gosmatch", "--protocol", "1", "--exclude",
                              "10", "--refine", "gicp", "--cache-dir", tmp_path / "c",
                              "--out", tmp_path / "r", "-q"], capsys)
    assert code == 0, err
    lines = [line for line in out.splitlines() if "n/a: the sequence holds objects" in line]
    assert len(lines) == 1 and lines[0].startswith("gosmatch:")
    row = json.loads((tmp_path / "r" / "metrics.json").read_text())["results"][0]
    assert row["refine"] is None and row["rr_kind"] == "full"  # GOSMatch's own poses still
