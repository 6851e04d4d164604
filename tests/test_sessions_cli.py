"""liris eval --query/--database end to end: all six methods, show, compare, plot, report."""

from __future__ import annotations

import json

import pytest
from conftest import assert_one_line_error, run_cli

SIX = "lidar-iris,scan-context,m2dp,esf,gosmatch,esm"


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from lidar_iris_eval.cli import main

    root = tmp_path_factory.mktemp("sessions-cli")
    try:
        main(["simulate", str(root / "w"), "--world", "tiny-mixed", "--frames", "40",
              "--azimuth-steps", "256", "--sessions", "2", "--session-sensor", "vlp16", "-q"])
    except SystemExit as exit_:
        assert exit_.code in (0, None)
    return root


@pytest.fixture(scope="module")
def run_dir(world):
    from lidar_iris_eval.cli import main

    out = world / "run"
    try:
        main(["eval", "--query", str(world / "w" / "session1"), "--database",
              str(world / "w" / "session0"), "--descriptor", SIX, "--out", str(out),
              "--cache-dir", str(world / "cache"), "-q"])
    except SystemExit as exit_:
        assert exit_.code in (0, None)
    return out


def test_two_sensor_run_reports_ranking_for_all_six_methods(run_dir):
    metrics = json.loads((run_dir / "metrics.json").read_text())
    rows = metrics["results"]
    assert sorted(r["descriptor"] for r in rows) == sorted(SIX.split(","))
    for r in rows:
        assert r["protocol"] == "cross-session"
        for key in ("recall_at_1", "recall_at_1pct", "mrr"):
            assert r[key] is not None and 0 <= r[key] <= 1, (r["descriptor"], key)
        assert len(r["recall_at_n"]) == 25
        assert r["n_database"] == 40
    assert "does not apply across sessions" in metrics["conventions"]["exclusion"]
    assert metrics["database"]["name"] == "session0"
    assert (run_dir / "cross_session" / "lidar-iris" / "ranks.csv").is_file()


def test_show_compare_plot_and_report_read_the_run(run_dir, world, capsys):
    code, out, err = run_cli(["show", run_dir], capsys)
    assert code == 0, err
    assert "recall_at_1pct" in out and "mrr" in out
    assert "does not apply across sessions" in out and "database session: session0" in out
    code, out, err = run_cli(["compare", run_dir, run_dir], capsys)
    assert code == 0, err
    assert "recall_at_1" in out and "0 metric value(s) differ" in out
    code, out, err = run_cli(["plot", run_dir, "--out", world / "figs"], capsys)
    assert code == 0, err
    assert (world / "figs" / "recall_at_n.png").is_file()
    assert (world / "figs" / "pr_cross_session.png").is_file()
    pytest.importorskip("plotly")
    code, out, err = run_cli(["report", run_dir, "--out", world / "report"], capsys)
    assert code == 0, err
    page = (world / "report" / "index.html").read_text()
    assert "recall-at-n" in page and "pr-cross-session" in page


def test_ranking_flag_recall_at_1_is_top1_accuracy(world, capsys):
    code, out, err = run_cli(["eval", world / "w" / "session0", "--protocol", "1", "--exclude",
                              "3", "--descriptor", "lidar-iris", "--ranking", "--json",
                              "--out", world / "ranked", "--cache-dir", world / "cache", "-q"],
                             capsys)
    assert code == 0, err
    row = json.loads(out)["results"][0]
    assert row["n_revisits"] > 10
    assert row["recall_at_1"] == pytest.approx(row["n_true_top1"] / row["n_revisits"])


def test_cross_session_errors_are_one_line(world, capsys):
    s0, s1 = world / "w" / "session0", world / "w" / "session1"
    code, _, err = run_cli(["eval", "--query", s1, "--descriptor", "m2dp"], capsys)
    assert_one_line_error(code, err, "--query/--database", "needs both")
    code, _, err = run_cli(["eval", "--query", s1, "--database", s0, "--protocol", "1",
                            "--descriptor", "m2dp"], capsys)
    assert_one_line_error(code, err, "--protocol", "does not apply")
    code, _, err = run_cli(["eval", s0, "--protocol", "1", "--descriptor", "m2dp",
                            "--convention", "wild-places-inter"], capsys)
    assert_one_line_error(code, err, "wild-places-inter", "--query and --database")
    (world / "bad.txt").write_text("1 2 3\n")
    code, _, err = run_cli(["eval", "--query", s1, "--database", s0, "--align",
                            world / "bad.txt", "--descriptor", "m2dp"], capsys)
    assert_one_line_error(code, err, "bad.txt", "12 or 16")


def test_sessions_plan_runs_every_ordered_pair(world, capsys):
    plan = world / "plan.yaml"
    plan.write_text("descriptors: [m2dp, scan-context]\nsessions: [w/session0, w/session1]\n")
    code, out, err = run_cli(["eval", "--plan", plan, "--out", world / "planned", "--cache-dir",
                              world / "cache", "-q"], capsys)
    assert code == 0, err
    summary = (world / "planned" / "summary.csv").read_text().splitlines()
    assert summary[0].startswith("query,database,descriptor")
    assert len(summary) == 1 + 2 * 2 + 2  # two ordered pairs x two methods, two means
    assert (world / "planned" / "00-session0-vs-session1" / "metrics.json").is_file()
    code, out, err = run_cli(["show", world / "planned" / "01-session1-vs-session0"], capsys)
    assert code == 0 and "cross-session" in out
    plan.write_text("pairs: [{query: w/session1}]\ndescriptors: m2dp\n")
    code, _, err = run_cli(["eval", "--plan", plan, "--out", world / "bad-plan"], capsys)
    assert_one_line_error(code, err, "plan.yaml", "needs query and database")


def test_gt_overlap_counts_and_caches(world, capsys):
    from lidar_iris_eval.simulate import simulate_sequence

    seq = simulate_sequence(world / "short", "tiny-same", frames=12, azimuth_steps=256)
    args = ["gt", seq, "--gt", "overlap", "--exclude", "2", "--cache-dir", world / "ocache",
            "--json"]
    code, out, err = run_cli(args, capsys)
    assert code == 0, err
    first = json.loads(out)
    assert first["overlap_from_cache"] is False
    assert first["overlap_positive_pairs"] > 0
    assert 0 < first["share_of_pose_pairs_with_overlap"] <= 1
    code, out, err = run_cli(args, capsys)
    assert json.loads(out)["overlap_from_cache"] is True
    code, _, err = run_cli(["gt", "--poses", seq / "poses.txt", "--gt", "overlap"], capsys)
    assert_one_line_error(code, err, "--gt overlap", "SEQUENCE")
