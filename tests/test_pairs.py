"""Pair lists: SSC's rule counted independently, file round trip, PR equal to protocol 2's."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_loop import loop_sequence

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.metrics import pr_curve
from lidar_iris_eval.evaluation.pairs import (
    SSCRule,
    pair_distances_of,
    read_pairs,
    score_pair_list,
    ssc_pairs,
    write_pairs,
)
from lidar_iris_eval.evaluation.protocol2 import protocol2
from lidar_iris_eval.extract import extract
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.matching.blocks import affinity_matrix


def _brute_force(xz, rule):
    """SSC's rule written out with plain loops over camera x and z."""
    pos, neg = [], []
    for i in range(len(xz)):
        for j in range(i):
            d = float(np.hypot(*(xz[i] - xz[j])))
            if d < rule.positive_radius and i - j > rule.min_gap:
                pos.append((i, j))
            if d > rule.negative_radius:
                neg.append((i, j))
    return pos, neg


def test_ssc_rule_counts_and_sampling():
    rng = np.random.default_rng(3)
    t = np.linspace(0, 4 * np.pi, 300)
    cam = np.c_[30 * np.cos(t), rng.normal(0, 0.3, 300), 30 * np.sin(t)]  # camera y is height
    rule = SSCRule(negative_ratio=3, seed=7)
    pairs = ssc_pairs(cam, rule, block=64)
    pos, neg = _brute_force(cam[:, [0, 2]], rule)
    got_pos = [tuple(p) for p in pairs[pairs[:, 2] == 1, :2].tolist()]
    got_neg = pairs[pairs[:, 2] == 0, :2]
    assert sorted(got_pos) == sorted(pos) and len(pos) > 50
    assert len(got_neg) == 3 * len(pos)
    assert set(map(tuple, got_neg.tolist())) <= set(neg)
    assert len(set(map(tuple, got_neg.tolist()))) == len(got_neg)  # without replacement
    np.testing.assert_array_equal(pairs, ssc_pairs(cam, rule, block=1000))  # same seed
    assert not np.array_equal(pairs, ssc_pairs(cam, SSCRule(negative_ratio=3, seed=8)))


def test_pair_file_round_trip_and_errors(tmp_path):
    pairs = np.array([[60, 2, 1], [70, 1, 0]])
    write_pairs(tmp_path / "p.txt", pairs)
    assert (tmp_path / "p.txt").read_text().splitlines()[0] == "000060 000002 1"
    np.testing.assert_array_equal(read_pairs(tmp_path / "p.txt", 100), pairs)
    for text, fragment in [("1 2\n", "expected 'i j label'"), ("1 2 5\n", "label must be"),
                           ("1 200 1\n", "out of range"), ("a 2 1\n", "integers"),
                           ("# only a comment\n", "no pairs"), ("3 3 1\n", "itself")]:
        (tmp_path / "bad.txt").write_text(text)
        with pytest.raises(LirisError, match=fragment):
            read_pairs(tmp_path / "bad.txt", 100)


def _protocol2_distances(desc, descriptors):
    """The float64 distances protocol 2 counts (the blocks its streamed pass sees)."""
    n = len(descriptors)
    full = np.full((n, n), np.nan)

    def sink(a, b, d):
        full[a:b, :d.shape[1]] = d

    affinity_matrix(desc, descriptors, None, sink=sink, store=False)
    return full


@pytest.mark.parametrize("method", ["scan-context", "lidar-iris", "m2dp"])
def test_pair_list_pr_equals_protocol2_restricted_to_the_pairs(tmp_path, method):
    seq = open_sequence(loop_sequence(tmp_path / "loop", frames=70))
    desc = get_descriptor(method)
    db = extract(seq, desc)
    # an SSC-style list on this small loop: 3 m and a gap of 30 frames, 20 m negatives x 4
    rule = SSCRule(min_gap=30, negative_ratio=4, seed=1, distance="planar", pose_frame="lidar")
    pairs = ssc_pairs(seq.positions("lidar"), rule)
    assert np.count_nonzero(pairs[:, 2]) >= 5
    scored = score_pair_list(pairs, pair_distances_of(desc, desc.prepare(db.descriptors), pairs))
    matrix = _protocol2_distances(desc, db.descriptors)
    # rows are the later frame: a symmetric pass fills the lower triangle, where i > j lies
    restricted = pr_curve(matrix[pairs[:, 0], pairs[:, 1]], pairs[:, 2] == 1,
                          int(np.count_nonzero(pairs[:, 2])))
    # and protocol 2 itself, over every pair, is the same pass
    p2 = protocol2(desc, db, seq.positions("lidar"), radius=3.0, distance="planar",
                   frame="lidar")
    assert p2.metrics["n_pairs"] == 70 * 69
    np.testing.assert_array_equal(scored.curve.tp, restricted.tp)
    np.testing.assert_array_equal(scored.curve.fp, restricted.fp)
    np.testing.assert_array_equal(scored.curve.precision, restricted.precision)
    np.testing.assert_array_equal(scored.curve.recall, restricted.recall)
    np.testing.assert_array_equal(scored.curve.threshold, restricted.threshold)
    assert scored.metrics["n_pairs"] == len(pairs)


def test_cli_pairs_file_and_ssc_rule_agree(tmp_path, capsys):
    import json

    from conftest import assert_one_line_error, run_cli

    root = loop_sequence(tmp_path / "loop", frames=70)
    seq = open_sequence(root)
    rule = SSCRule(min_gap=50, negative_ratio=10, seed=0,
                   pose_frame="camera")  # what --pairs ssc uses
    pairs = ssc_pairs(seq.positions("camera"), rule)
    write_pairs(tmp_path / "list.txt", pairs)
    outs = []
    for k, value in enumerate([str(tmp_path / "list.txt"), "ssc"]):
        code, out, err = run_cli(["eval", root, "--pairs", value, "--descriptor", "m2dp",
                                  "--json", "--out", tmp_path / f"run{k}", "--cache-dir",
                                  tmp_path / "cache", "-q"], capsys)
        assert code == 0, err
        outs.append(json.loads(out)["results"][0])
    for key in ("ap", "f1_max", "r100p", "n_pairs", "n_positives"):
        assert outs[0][key] == outs[1][key]
    assert outs[0]["n_positives"] == int(pairs[:, 2].sum()) > 0
    code, _, err = run_cli(["eval", root, "--pairs", "ssc", "--protocol", "1",
                            "--descriptor", "m2dp"], capsys)
    assert_one_line_error(code, err, "--protocol", "does not apply")
