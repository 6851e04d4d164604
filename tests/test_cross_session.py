"""Cross-session evaluation and the ranking pass within one sequence."""

from __future__ import annotations

import numpy as np
import pytest
from synthetic_loop import loop_sequence

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.cross_session import (
    EXCLUSION_RULE,
    align_poses,
    cross_positives,
    evaluate_sessions,
    read_transform,
)
from lidar_iris_eval.evaluation.ground_truth import database_limits
from lidar_iris_eval.evaluation.protocol1 import protocol1
from lidar_iris_eval.evaluation.settings import Settings
from lidar_iris_eval.extract import extract
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.simulate import resolve_config
from lidar_iris_eval.simulate.sessions import run_sessions


@pytest.fixture(scope="module")
def loop(tmp_path_factory):
    return open_sequence(loop_sequence(tmp_path_factory.mktemp("loop") / "seq", frames=70))


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    """tiny-mixed driven twice, 60 scans each, HDL-64E then VLP-16 (256 azimuth steps)."""
    root = tmp_path_factory.mktemp("sessions") / "world"
    cfg = resolve_config("tiny-mixed", {"frames": 60, "azimuth_steps": 256})
    run_sessions(root, cfg, 2, ("vlp16",))
    return [open_sequence(root / f"session{k}") for k in (0, 1)]


@pytest.mark.parametrize("method", ["lidar-iris", "gosmatch"])
def test_recall_at_1_is_protocol1_top1_on_the_same_sequence(loop, sessions, method):
    desc = get_descriptor(method)
    seq = loop if method == "lidar-iris" else sessions[0]
    # the loop revisits after a lap; the simulated drive only has its own recent past
    exclude, radius = (10, 4.0) if method == "lidar-iris" else (3, 4.0)
    db = extract(seq, desc)
    positions = seq.positions("camera")
    p1 = protocol1(desc, db, positions, exclude=exclude, radius=radius)
    limits = database_limits(len(seq), Settings(exclude=exclude, radius=radius))
    positives = cross_positives(positions, positions, radius)
    res = evaluate_sessions(desc, db, db, positives, limits=limits, same_sequence=True)
    m1 = p1.metrics
    assert m1["n_revisits"] > 5
    assert res.metrics["n_ranking_queries"] == m1["n_revisits"]
    assert res.metrics["recall_at_1"] == pytest.approx(m1["n_true_top1"] / m1["n_revisits"])
    queries = p1.matches.query
    np.testing.assert_array_equal(res.match[queries], p1.matches.match)
    assert "exclusion" not in res.metrics  # the window applied here


def test_cross_session_positives_ignore_the_window_and_say_so(loop):
    desc = get_descriptor("m2dp")
    db = extract(loop, desc)
    positions = loop.positions("lidar")
    # queries: the second half; database: the first half (two "sessions" of one world)
    q, d = np.arange(35, 70), np.arange(35)
    positives = cross_positives(positions[q], positions[d], 4.0)
    res = evaluate_sessions(desc, db.descriptors[q], db.descriptors[d], positives)
    assert res.metrics["exclusion"] == EXCLUSION_RULE
    assert res.metrics["n_database"] == 35 and res.metrics["n_queries"] == 35
    n_pos = sum(len(p) > 0 for p in positives)
    assert res.metrics["n_ranking_queries"] == n_pos > 0
    for key in ("recall_at_1", "recall_at_1pct", "mrr"):
        assert res.metrics[key] is not None
    # brute force: rank of the first positive in the sorted distance row
    dist = np.array([[desc.distance(db.descriptors[i], db.descriptors[j])[0] for j in d]
                     for i in q])
    expected = []
    for r, pos in enumerate(positives):
        if len(pos):
            order = np.lexsort((np.arange(35), dist[r]))
            expected.append(int(np.nonzero(np.isin(order, pos))[0][0]) + 1)
    got = res.ranks.rank[res.ranks.has_positive]
    np.testing.assert_array_equal(got, expected)
    assert res.metrics["mrr"] == pytest.approx(np.mean(1 / np.array(expected)))


def test_alignment_moves_the_query_session(tmp_path):
    poses = np.stack([np.eye(4)] * 2)
    poses[1, 0, 3] = 5.0
    move = np.eye(4)
    move[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    move[:3, 3] = [1, 2, 3]
    out = align_poses(poses, move)
    np.testing.assert_allclose(out[1, :3, 3], [1, 7, 3])
    (tmp_path / "t.txt").write_text(" ".join(map(str, move[:3].ravel())))
    np.testing.assert_allclose(read_transform(tmp_path / "t.txt"), move)
    (tmp_path / "bad.txt").write_text("1 2 3")
    with pytest.raises(LirisError, match="12 or 16"):
        read_transform(tmp_path / "bad.txt")
    skew = move.copy()
    skew[0, 0] = 2.0
    (tmp_path / "skew.txt").write_text(" ".join(map(str, skew.ravel())))
    with pytest.raises(LirisError, match="rotation"):
        read_transform(tmp_path / "skew.txt")


METHODS = ["lidar-iris", "scan-context", "m2dp", "esf", "gosmatch", "esm"]


@pytest.mark.parametrize("method", METHODS)
def test_two_sensor_sessions_report_ranking_metrics_for_every_method(sessions, method):
    query, database = sessions[1], sessions[0]
    desc = get_descriptor(method)
    q_db, d_db = extract(query, desc), extract(database, desc)
    positives = cross_positives(query.positions("camera"), database.positions("camera"), 4.0)
    res = evaluate_sessions(desc, q_db, d_db, positives)
    m = res.metrics
    assert m["n_ranking_queries"] == sum(len(p) > 0 for p in positives) > 40
    for key in ("recall_at_1", "recall_at_1pct", "mrr"):
        assert m[key] is not None and 0.0 <= m[key] <= 1.0, (key, m[key])
    assert m["recall_1pct_n"] == 1  # 60 database scans
    assert m["recall_at_1pct"] == m["recall_at_1"]
    assert m["mrr"] >= m["recall_at_1"]
