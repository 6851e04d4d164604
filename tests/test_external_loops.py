"""Issue 35: a run's own matches.csv / --export-loops .txt scored as an external system's loops."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from conftest import run_cli
from synthetic_loop import loop_sequence

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.external_loops import evaluate_loops
from lidar_iris_eval.evaluation.settings import Settings
from lidar_iris_eval.io.loops import read_loops


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("loops")
    seq = loop_sequence(root / "seq")
    out = root / "run"
    code, _, err = run_cli(["eval", seq, "--descriptor", "scan-context,m2dp", "--protocol", "1",
                            "--exclude", "10", "--out", out, "--cache-dir", root / "cache",
                            "--export-loops", root / "loops.txt", "--quiet"], _Capsys())
    assert code == 0, err
    return seq, out, root / "loops.txt"


class _Capsys:  # run_cli needs only readouterr; module-scoped fixtures cannot take capsys
    def readouterr(self):
        class R:
            out = err = ""
        return R()


@pytest.mark.parametrize("k, name", [(0, "scan-context"), (1, "m2dp")])
def test_matches_csv_reproduces_protocol1(run, k, name):
    seq, out, _ = run
    row = json.loads((out / "metrics.json").read_text())["results"][k]
    assert row["descriptor"] == name
    ev = evaluate_loops(seq, [out / f"protocol1/{name}/matches.csv"], Settings(exclude=10))
    mine = ev.rows[0]
    assert mine["descriptor"] == "loops:matches"
    for key in ("ap", "f1_max", "r100p", "ep", "n_revisits", "n_true_top1"):
        assert mine[key] == row[key], key
    print(name, {key: row[key] for key in ("ap", "f1_max", "r100p")})


def test_export_txt_gives_precision_recall_at_f1max(run):
    seq, out, txt = run
    pr = pd.read_csv(out / "protocol1/scan-context/pr.csv")
    row = json.loads((out / "metrics.json").read_text())["results"][0]
    at = pr[pr.threshold == row["f1_threshold"]].iloc[0]
    ev = evaluate_loops(seq, [txt.with_name("loops-scan-context.txt")], Settings(exclude=10))
    mine = ev.rows[0]
    assert read_loops(txt.with_name("loops-scan-context.txt")).format == "liris-txt"
    assert mine["loops_precision"] == pytest.approx(at.precision, abs=1e-12)
    assert mine["loops_recall"] == pytest.approx(at.recall, abs=1e-12)


def test_bad_pair_line_names_file_and_line(tmp_path, run):
    seq, _, _ = run
    bad = tmp_path / "pairs.txt"
    bad.write_text("30 2 0.1\n31 x 0.2\n")
    with pytest.raises(LirisError, match=r"pairs.txt:2"):
        read_loops(bad)
    past = tmp_path / "past.txt"
    past.write_text("30 2\n999 3\n")
    with pytest.raises(LirisError, match=r"past.txt:2.*999"):
        evaluate_loops(seq, [past], Settings(exclude=10))


def test_g2o_loop_edges_and_one_based_pairs_agree(tmp_path, run):
    seq, _, _ = run
    P = np.loadtxt(seq / "poses.txt").reshape(-1, 3, 4)
    n = len(P)
    lines = [f"VERTEX_SE3:QUAT {k} 0 0 0 0 0 0 1" for k in range(n)]
    lines += [f"EDGE_SE3:QUAT {k} {k + 1} 1 0 0 0 0 0 1" for k in range(n - 1)]
    # one lap is 70 / 1.3 frames: frame q revisits q - 54; plus a planted false loop
    loops = [(60, 6), (65, 11), (40, 5)]
    lines += [f"EDGE_SE3:QUAT {q} {m} 0 0 0 0 0 0 1" for q, m in loops]
    (tmp_path / "g.g2o").write_text("\n".join(lines) + "\n")
    (tmp_path / "p.txt").write_text("".join(f"{q + 1} {m + 1}\n" for q, m in loops))
    ev = evaluate_loops(seq, [tmp_path / "g.g2o", tmp_path / "p.txt"], Settings(exclude=10),
                        formats=["g2o", "pairs"], index_base=0)
    g, p = ev.rows
    assert g["n_odometry_edges"] == n - 1
    d = np.linalg.norm(P[[60, 65, 40], :, 3] - P[[6, 11, 5], :, 3], axis=1)
    expected_tp = int(np.count_nonzero(d < 4.0))
    assert g["loops_tp"] == expected_tp and g["loops_fp"] == 3 - expected_tp
    # the pair list read 0-based is off by one frame: read it 1-based to agree
    ev1 = evaluate_loops(seq, [tmp_path / "p.txt"], Settings(exclude=10), index_base=1)
    assert ev1.rows[0]["loops_tp"] == g["loops_tp"]
    assert p["n_loops"] == 3


def _naive_ap(is_true: np.ndarray, distance: np.ndarray, n_positives: int) -> float:
    """AP = sum (R_k - R_{k-1}) P_k, one query at a time (distinct distances)."""
    order = np.argsort(distance)
    tp = fp = 0
    ap = recall_before = 0.0
    for k in order:
        tp, fp = tp + int(is_true[k]), fp + int(not is_true[k])
        recall = tp / n_positives
        ap += (recall - recall_before) * tp / (tp + fp)
        recall_before = recall
    return ap


def test_shuffled_scores_match_an_independent_ap(run, tmp_path):
    # the run's methods are perfect here (AP 1), so shuffle the distances: AP then differs
    # from 1 and is checked against a hand-written AP over the revisit count
    seq, out, _ = run
    table = pd.read_csv(out / "protocol1/scan-context/matches.csv")
    rng = np.random.default_rng(3)
    table["distance"] = rng.permutation(len(table)) + 1.0
    table.to_csv(tmp_path / "shuffled.csv", index=False)
    row = evaluate_loops(seq, [tmp_path / "shuffled.csv"], Settings(exclude=10)).rows[0]
    expected = _naive_ap(table.is_true.to_numpy(bool), table.distance.to_numpy(),
                         int(table.is_revisit.sum()))
    assert 0.1 < expected < 0.9
    assert row["ap"] == pytest.approx(expected, abs=1e-12)


def test_cli_loops_run_and_bad_file(run, tmp_path, capsys):
    from conftest import assert_one_line_error

    seq, out, txt = run
    matches = out / "protocol1/m2dp/matches.csv"
    code, stdout, err = run_cli(["eval", seq, "--loops", matches, "--loops",
                                 txt.with_name("loops-scan-context.txt"), "--exclude", "10",
                                 "--out", tmp_path / "lr"], capsys)
    assert code == 0, err
    rows = json.loads((tmp_path / "lr/metrics.json").read_text())["results"]
    assert [r["descriptor"] for r in rows] == ["loops:matches", "loops:loops-scan-context"]
    code, stdout, err = run_cli(["show", tmp_path / "lr"], capsys)
    assert code == 0 and "loops:matches" in stdout
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 9 0 0 0 0 0 0 1\n")
    code, _, err = run_cli(["eval", seq, "--loops", bad, "--out", tmp_path / "x"], capsys)
    assert_one_line_error(code, err, "bad.g2o:2", "vertex 9")
