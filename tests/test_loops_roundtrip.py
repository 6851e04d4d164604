"""Issue 35's round trips on a simulated sequence where the methods are not perfect: a run's
matches.csv scored with --loops gives its protocol 1 numbers exactly, its --export-loops files
(.txt and .tum) give its precision and recall at F1max, a scored 1-based pair list gives its AP
and F1max; bad input is one error line naming file and line."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from conftest import assert_one_line_error, run_cli

EXCLUDE = "30"


class _Capsys:  # module-scoped fixtures cannot take capsys
    def readouterr(self):
        class R:
            out = err = ""
        return R()


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    root = tmp_path_factory.mktemp("roundtrip")
    seq = simulate_sequence(root / "sim", "tiny-mixed", frames=120, sensor="vlp16",
                            azimuth_steps=360)
    code, _, err = run_cli(["eval", seq, "--descriptor", "scan-context,m2dp", "--protocol", "1",
                            "--exclude", EXCLUDE, "--out", root / "run", "--cache-dir",
                            root / "cache", "--export-loops", root / "loops.txt", "--quiet"],
                           _Capsys())
    assert code == 0, err
    code, _, err = run_cli(["eval", seq, "--descriptor", "scan-context", "--protocol", "1",
                            "--exclude", EXCLUDE, "--out", root / "run-tum", "--cache-dir",
                            root / "cache", "--export-loops", root / "loops.tum", "--quiet"],
                           _Capsys())
    assert code == 0, err
    rows = json.loads((root / "run" / "metrics.json").read_text())["results"]
    return seq, root, {r["descriptor"]: r for r in rows}


def _loops_run(seq, out, capsys, *args):
    code, _, err = run_cli(["eval", seq, "--exclude", EXCLUDE, "--out", out, *args], capsys)
    assert code == 0, err
    return json.loads((out / "metrics.json").read_text())["results"]


@pytest.mark.parametrize("name", ["scan-context", "m2dp"])
def test_matches_csv_reproduces_a_nontrivial_run(run, tmp_path, capsys, name):
    seq, root, rows = run
    row = rows[name]
    assert row["ap"] < 0.99 and row["f1_max"] < 0.99  # a real PR curve, not a perfect one
    mine = _loops_run(seq, tmp_path / "l", capsys, "--loops",
                      root / f"run/protocol1/{name}/matches.csv")[0]
    print(name, {k: row[k] for k in ("ap", "f1_max", "r100p")})
    for key in ("ap", "f1_max", "r100p", "ep", "n_revisits", "n_true_top1"):
        assert mine[key] == row[key], key


@pytest.mark.parametrize("suffix", ["txt", "tum"])
def test_export_gives_precision_recall_at_f1max(run, tmp_path, capsys, suffix):
    seq, root, rows = run
    folder = root / ("run" if suffix == "txt" else "run-tum")
    row = rows["scan-context"]
    pr = pd.read_csv(folder / "protocol1/scan-context/pr.csv")
    at = pr[pr.threshold == row["f1_threshold"]].iloc[0]
    assert at.precision < 1 or at.recall < 1
    export = root / ("loops-scan-context.txt" if suffix == "txt" else "loops.tum")
    mine = _loops_run(seq, tmp_path / "l", capsys, "--loops", export)[0]
    print(suffix, at.precision, at.recall, mine["loops_tp"], mine["loops_fp"])
    assert mine["loops_precision"] == pytest.approx(at.precision, abs=1e-12)
    assert mine["loops_recall"] == pytest.approx(at.recall, abs=1e-12)


def test_scored_one_based_pairs_give_the_same_ap_f1(run, tmp_path, capsys):
    seq, root, rows = run
    table = pd.read_csv(root / "run/protocol1/m2dp/matches.csv")
    has = table.match >= 0
    pairs = tmp_path / "pairs.txt"
    pairs.write_text("".join(f"{q + 1} {m + 1} {d!r}\n" for q, m, d in
                             zip(table["query"][has], table["match"][has], table["distance"][has],
                                 strict=True)))
    mine = _loops_run(seq, tmp_path / "l", capsys, "--loops", pairs, "--loops-index-base", "1")[0]
    assert mine["ap"] == rows["m2dp"]["ap"]
    assert mine["f1_max"] == rows["m2dp"]["f1_max"]


@pytest.mark.parametrize("name, text, fragments", [
    ("missing.g2o", "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n"
                    "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1\nEDGE_SE3:QUAT 1 40 0 0 0 0 0 0 1\n",
     ["missing.g2o:4", "vertex 40"]),
    ("malformed.txt", "60 2 0.1\n61 3\n62 x 0.2\n", ["malformed.txt:3", "'x'"]),
    ("past.txt", "60 2\n500 3\n", ["past.txt:2", "500"]),
    ("late.tum", "# t_q t_m\n10.0 1.0\n9999.0 1.0\n", ["late.tum:3", "matches no scan"]),
    ("short.g2o", "VERTEX_SE3:QUAT 0 0 0 0 0 0 1\n", ["short.g2o:1", "8 fields"]),
])
def test_bad_loop_file_is_one_line(run, tmp_path, capsys, name, text, fragments):
    seq, _, _ = run
    path = tmp_path / name
    path.write_text(text)
    code, _, err = run_cli(["eval", seq, "--exclude", EXCLUDE, "--loops", path, "--out",
                            tmp_path / "x"], capsys)
    assert_one_line_error(code, err, *fragments)
    assert not (tmp_path / "x").exists()


def test_sequence_times_are_the_tum_clock(run):
    seq, _, _ = run
    times = np.loadtxt(seq / "times.txt")
    assert times[0] < 10.0 < times[-1] and times[-1] < 9999.0  # late.tum's 2nd line is placed


def test_g2o_with_other_records_skips_them_with_one_warning(run, tmp_path, capsys):
    seq, _, _ = run
    graph = tmp_path / "graph.g2o"  # hdl_graph_slam also writes a floor plane and its edges
    graph.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n"
                     "VERTEX_SE3:QUAT 60 0 0 0 0 0 0 1\nVERTEX_PLANE 200 0 0 1 0\n"
                     "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1\nEDGE_SE3_PLANE 0 200 0 0 1 0 1 0 0 1 0 1\n"
                     "EDGE_SE3:QUAT 60 0 0 0 0 0 0 0 1\n")
    code, _, err = run_cli(["eval", seq, "--exclude", EXCLUDE, "--loops", graph,
                            "--no-posegraph", "--out", tmp_path / "r"], capsys)
    assert code == 0, err
    warnings = [line for line in err.splitlines() if "skipped records" in line]
    assert len(warnings) == 1 and "1 EDGE_SE3_PLANE" in warnings[0] \
        and "1 VERTEX_PLANE" in warnings[0]
    row = json.loads((tmp_path / "r" / "metrics.json").read_text())["results"][0]
    assert row["n_loops"] == 1
