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


#: the README's quick-start table (AP, F1max, R@100P, EP), to its 3 decimals; a change
#: of any descriptor's numbers on this sequence must update the README with it
README_TABLE = {
    (1, "lidar-iris"): (0.965, 0.972, 0.946, 0.973),
    (1, "scan-context"): (0.995, 0.995, 0.990, 0.995),
    (1, "m2dp"): (0.118, 0.207, 0.025, 0.512),
    (1, "esf"): (0.189, 0.309, 0.030, 0.515),
    (2, "lidar-iris"): (0.847, 0.807, 0.518, 0.759),
    (2, "scan-context"): (0.916, 0.902, 0.638, 0.819),
    (2, "m2dp"): (0.214, 0.238, 0.014, 0.507),
    (2, "esf"): (0.166, 0.208, 0.003, 0.502),
}
#: README: top-1 accuracy of protocol 1 on the same- / reverse-direction revisits
README_TOP1 = {"lidar-iris": (0.92, 1.00), "scan-context": (0.99, 1.00),
               "m2dp": (0.53, 0.03), "esf": (0.29, 0.44)}


@pytest.mark.parametrize("key", sorted(README_TABLE))
def test_metrics_equal_the_readme_table(small_mixed_run, key):
    _, rows = small_mixed_run
    row = rows[key]
    got = tuple(round(row[k], 3) for k in ("ap", "f1_max", "r100p", "ep"))
    assert got == README_TABLE[key]


@pytest.mark.parametrize("name", sorted(README_TOP1))
def test_top1_by_direction_equals_the_readme(small_mixed_run, name):
    _, rows = small_mixed_run
    row = rows[(1, name)]
    assert (row["n_revisits_same"], row["n_revisits_reverse"]) == (85, 118)
    assert (round(row["top1_same"], 2), round(row["top1_reverse"], 2)) == README_TOP1[name]


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
