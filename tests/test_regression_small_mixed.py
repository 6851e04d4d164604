"""CI regression: the built-in ``small-mixed`` sequence through all four descriptors.

This is the project's end-to-end check that the paper's headline claims hold
on data whose answer we know: LiDAR Iris finds the loops (protocol 1 max F1 at
least 0.9) and, unlike M2DP, also the reverse-direction ones; protocol 2
counts equal the ground truth of ``liris gt``.
"""

from __future__ import annotations

import json

import pytest

from lidar_iris_eval.cli import main
from lidar_iris_eval.simulate import simulate_sequence

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def small_mixed_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("small-mixed")
    seq = simulate_sequence(root / "seq", preset="small-mixed")
    run = root / "run"
    args = ["eval", str(seq), "--protocol", "1", "--protocol", "2",
            "--descriptor", "lidar-iris,scan-context,m2dp,esf",
            "--cache-dir", str(root / "cache"), "--out", str(run), "--quiet"]
    main(args)  # a failure exits with code 2 and fails the fixture
    metrics = json.loads((run / "metrics.json").read_text())
    rows = {(r["protocol"], r["descriptor"]): r for r in metrics["results"]}
    return seq, rows


def _gt(seq, capsys):
    capsys.readouterr()
    main(["gt", str(seq), "--json"])
    return json.loads(capsys.readouterr().out)


def test_all_descriptors_ran_both_protocols(small_mixed_run):
    _, rows = small_mixed_run
    for name in ("lidar-iris", "scan-context", "m2dp", "esf"):
        for protocol in (1, 2):
            assert 0.0 <= rows[(protocol, name)]["f1_max"] <= 1.0


def test_lidar_iris_finds_the_loops(small_mixed_run):
    _, rows = small_mixed_run
    assert rows[(1, "lidar-iris")]["f1_max"] >= 0.9


def test_lidar_iris_beats_m2dp_on_reverse_revisits(small_mixed_run):
    _, rows = small_mixed_run
    iris, m2dp = rows[(1, "lidar-iris")], rows[(1, "m2dp")]
    assert iris["n_revisits_reverse"] > 50 and iris["n_revisits_same"] > 50
    assert iris["top1_reverse"] > m2dp["top1_reverse"] + 0.5


def test_protocol2_counts_equal_liris_gt(small_mixed_run, capsys):
    seq, rows = small_mixed_run
    gt = _gt(seq, capsys)
    p2 = rows[(2, "lidar-iris")]
    assert p2["n_positives"] == gt["positive_ordered_pairs"]
    assert p2["n_pairs"] == gt["positive_ordered_pairs"] + gt["negative_ordered_pairs"]
    assert rows[(1, "lidar-iris")]["n_revisits"] == gt["revisit_queries"]
