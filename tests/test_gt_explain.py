"""``liris gt --explain I J`` and ``--diff A B`` (issue 38 items 1 and 2).

Expectations are computed here from the raw pose file with NumPy (brute force),
not with the library's ground-truth functions.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli


def _kitti_positions(kitti_dir):
    rows = np.loadtxt(kitti_dir / "poses" / "00.txt")
    return rows[:, [3, 7, 11]]


def _brute_revisits(coords: np.ndarray, radius: float, exclude: int, last_frame: bool = True):
    """Revisit flags by brute force: some j <= i - E strictly within ``radius``."""
    n = len(coords)
    out = np.zeros(n, bool)
    for start in range(0, n, 512):
        rows = np.arange(start, min(n, start + 512))
        d = np.linalg.norm(coords[rows, None, :] - coords[None, :, :], axis=2)
        allowed = np.arange(n)[None, :] <= rows[:, None] - exclude
        out[rows] = np.any((d < radius) & allowed, axis=1)
    if not last_frame:
        out[-1] = False
    return out


def _explain(kitti_dir, capsys, i, j, calib=True):
    args = ["gt", "--poses", kitti_dir / "poses" / "00.txt", "--explain", i, j, "--json"]
    if calib:
        args += ["--calib", kitti_dir / "calib" / "00.txt"]
    code, out, err = run_cli(args, capsys)
    assert code == 0, err
    return json.loads(out)


def test_explain_pair_near_4_5_m_splits_4_m_from_5_m_presets(kitti_dir, capsys):
    from lidar_iris_eval.evaluation.conventions import PRESETS

    cam = _kitti_positions(kitti_dir)
    # a pair ~4.5 m apart (3-D and planar), far apart in time, early frame in every
    # BEVPlace database and late frame a query of every BEVPlace split
    late, early = np.arange(3600, len(cam))[:, None], np.arange(600)[None, :]
    d3 = np.linalg.norm(cam[late] - cam[early], axis=2)
    dp = np.linalg.norm(cam[late][..., [0, 2]] - cam[early][..., [0, 2]], axis=2)
    score = np.abs(d3 - 4.5) + np.abs(dp - 4.5)
    a, b = np.unravel_index(np.argmin(score), score.shape)
    i, j = int(late[a, 0]), int(early[0, b])
    assert 4.3 < d3[a, b] < 4.7 and 4.3 < dp[a, b] < 4.7
    data = _explain(kitti_dir, capsys, i, j)
    assert data["pair"]["camera_3d_m"] == pytest.approx(d3[a, b], abs=1e-6)
    assert data["pair"]["camera_planar_m"] == pytest.approx(dp[a, b], abs=1e-6)
    assert data["pair"]["frames_apart"] == i - j
    rows = {r["convention"]: r for r in data["conventions"]}
    assert set(rows) == set(PRESETS)
    checked = 0
    for name, row in rows.items():
        if row["status"] == "unavailable":  # the seconds windows: KITTI poses carry no times
            assert PRESETS[name].exclude_seconds is not None and "times" in row["rule"]
            continue
        checked += 1
        if PRESETS[name].radius == 5.0:
            assert row["status"] == "positive", (name, row["rule"])
        else:
            assert PRESETS[name].radius == 4.0
            assert row["status"] == "negative", (name, row["rule"])
            assert row["decided_by"] == ["radius"]
            assert row["rule"].startswith("radius:") and "is not < 4 m" in row["rule"]
    assert checked >= 9
    assert rows["liris"]["status"] == "negative"
    assert rows["scancontext-eval"]["status"] == "positive"


def test_explain_stationary_span_names_the_e_rule(kitti_dir, capsys):
    cam = _kitti_positions(kitti_dir)
    step = np.linalg.norm(np.diff(cam, axis=0), axis=1)
    slow = int(np.argmin(step))  # KITTI 00 stops near frame 550 (traffic light)
    # a pair 35 frames apart within 4 m around the stop: positive at E = 30, not at E = 49
    cands = [k for k in range(max(0, slow - 60), slow + 60)
             if np.linalg.norm(cam[k + 35] - cam[k]) < 3.8]
    assert cands, "no slow span found"
    j = cands[0]
    i = j + 35
    rows = {r["convention"]: r for r in _explain(kitti_dir, capsys, i, j)["conventions"]}
    assert rows["liris"]["status"] == "positive"
    # i as a query: a revisit at E = 30 but not at E = 50 (brute force) is the stop's doing
    at30, at50 = _brute_revisits(cam, 4.0, 30), _brute_revisits(cam, 4.0, 50)
    assert rows["liris"]["i_revisit_query"] == bool(at30[i])
    assert at30[i] and not at50[i], "the pair should sit in KITTI 00's stop"
    assert "pseudo-revisit" in rows["liris"]["i_rule"] and "(E) decides" in rows["liris"]["i_rule"]
    far = {r["convention"]: r for r in _explain(kitti_dir, capsys, 4443, 3)["conventions"]}
    assert at50[4443] and "pseudo-revisit" not in far["liris"]["i_rule"]
    sc = rows["scancontext-eval"]
    assert sc["status"] == "negative" and sc["decided_by"] == ["E"]
    assert sc["rule"].startswith("E:") and "< E = 49" in sc["rule"]
    # the same pair 10 frames apart is negative under liris by E too
    rows = {r["convention"]: r for r in _explain(kitti_dir, capsys, j + 10, j)["conventions"]}
    assert rows["liris"]["decided_by"] == ["E"] and "< E = 30" in rows["liris"]["rule"]
    # i as a query: liris says revisit (a pseudo-revisit of the stop) and scancontext names E
    brute = _brute_revisits(cam, 4.0, 30)
    assert rows["liris"]["i_revisit_query"] == bool(brute[j + 10])


def test_explain_without_calib_marks_lidar_presets_unavailable(kitti_dir, capsys):
    data = _explain(kitti_dir, capsys, 4443, 3, calib=False)
    rows = {r["convention"]: r for r in data["conventions"]}
    assert rows["contour-context"]["status"] == "unavailable"
    assert "--calib" in rows["contour-context"]["rule"]
    assert data["pair"]["lidar_3d_m"] is None


def test_explain_text_and_bad_frames(kitti_dir, capsys):
    poses = kitti_dir / "poses" / "00.txt"
    code, out, _ = run_cli(["gt", "--poses", poses, "--explain", 4443, 3], capsys)
    assert code == 0
    assert "liris: negative - radius:" in out and "scancontext-eval: positive" in out
    code, _, err = run_cli(["gt", "--poses", poses, "--explain", 4541, 3], capsys)
    assert_one_line_error(code, err, "--explain I=4541", "0..4540")
    code, _, err = run_cli(["gt", "--poses", poses, "--explain", 3, 3], capsys)
    assert_one_line_error(code, err, "two different frames")
    code, _, err = run_cli(["gt", "--poses", poses, "--explain", 5, 3, "--radius", "5"], capsys)
    assert_one_line_error(code, err, "--radius")


def test_explain_reports_overlap_on_real_scans(kitti_dir, capsys):
    code, out, err = run_cli(["gt", kitti_dir / "samples" / "00", "--explain", 1, 0, "--json"],
                             capsys)
    assert code == 0, err
    near = json.loads(out)["pair"]
    code, out, _ = run_cli(["gt", kitti_dir / "samples" / "00", "--explain", 2, 0, "--json"],
                           capsys)
    far = json.loads(out)["pair"]
    # frames 94 and 95 are neighbours; 198 is another place
    assert near["overlap_positive"] and near["overlap_i_j"] > 0.3
    assert far["overlap_i_j"] < near["overlap_i_j"]


def _counts(kitti_dir, capsys, name):
    code, out, _ = run_cli(["gt", "--poses", kitti_dir / "poses" / "00.txt", "--convention",
                            name, "--json"], capsys)
    assert code == 0
    data = json.loads(out)
    return data["positive_ordered_pairs"], data["revisit_queries"]


def test_diff_equals_difference_of_gt_counts(kitti_dir, capsys, tmp_path):
    pa, ra = _counts(kitti_dir, capsys, "liris")
    pb, rb = _counts(kitti_dir, capsys, "scancontext-eval")
    out_csv, out_png = tmp_path / "diff.csv", tmp_path / "diff.png"
    code, out, err = run_cli(["gt", "--poses", kitti_dir / "poses" / "00.txt", "--diff", "liris",
                              "scancontext-eval", "--diff-csv", out_csv, "--diff-plot", out_png,
                              "--json"], capsys)
    assert code == 0, err
    d = json.loads(out)
    assert (ra, rb) == (816, 803)
    assert d["revisit_queries_only_a"] - d["revisit_queries_only_b"] == ra - rb
    assert d["positive_ordered_pairs_only_a"] - d["positive_ordered_pairs_only_b"] == pa - pb
    assert d["revisit_queries_a_minus_b"] == ra - rb
    # the differing queries, independently by brute force
    cam = _kitti_positions(kitti_dir)
    a = _brute_revisits(cam, 4.0, 30)
    b = _brute_revisits(cam[:, [0, 2]], 5.0, 49, last_frame=False)
    with out_csv.open() as fh:
        rows = list(csv.DictReader(fh))
    only_a = {int(r["i"]) for r in rows if r["kind"] == "revisit_query" and r["only_in"] == "a"}
    only_b = {int(r["i"]) for r in rows if r["kind"] == "revisit_query" and r["only_in"] == "b"}
    assert only_a == set(np.flatnonzero(a & ~b).tolist())
    assert only_b == set(np.flatnonzero(b & ~a).tolist())
    # the deciding rule, independently: does B with A's window (E = 30, every frame a query)
    # count the query, or B with A's radius and distance (4 m, 3-D)?
    b_window = _brute_revisits(cam[:, [0, 2]], 5.0, 30)
    a_radius = _brute_revisits(cam, 4.0, 49, last_frame=False)
    for r in rows:
        if r["kind"] != "revisit_query":
            continue
        q = int(r["i"])
        if r["only_in"] == "a":
            expected = "E" if b_window[q] else ("radius" if a_radius[q] else None)
        else:  # A (liris) with B's radius-and-frame, or B's window
            expected = "radius" if b_window[q] else None
        if expected is not None:
            assert expected in r["decided_by"], (q, r["decided_by"], r["why_not_in_other"])
    pairs = [r for r in rows if r["kind"] == "positive_pair"]
    assert 2 * len(pairs) == (d["positive_ordered_pairs_only_a"]
                              + d["positive_ordered_pairs_only_b"])
    for r in pairs[:50]:  # a 5 m planar pair that is not a 4 m 3-D one
        i, j = int(r["i"]), int(r["j"])
        assert np.linalg.norm(cam[i, [0, 2]] - cam[j, [0, 2]]) < 5.0
        assert np.linalg.norm(cam[i] - cam[j]) >= 4.0
    assert out_png.stat().st_size > 10_000 and out_png.read_bytes()[:4] == b"\x89PNG"


def test_diff_never_replaces_a_file_silently(kitti_dir, capsys, tmp_path):
    target = tmp_path / "mine.csv"
    target.write_text("my data\n")
    args = ["gt", "--poses", kitti_dir / "poses" / "00.txt", "--diff", "liris", "iris-cpp",
            "--diff-csv", target]
    code, _, err = run_cli(args, capsys)
    assert_one_line_error(code, err, "already exists", "--overwrite")
    assert target.read_text() == "my data\n"
    code, _, err = run_cli([*args, "--overwrite"], capsys)
    assert code == 0, err
    assert target.read_text().startswith("kind,only_in")
    code, _, err = run_cli(["gt", "--poses", kitti_dir / "poses" / "00.txt", "--diff", "liris",
                            "nope"], capsys)
    assert_one_line_error(code, err, "--diff B=nope")
    code, _, err = run_cli(["gt", "--poses", kitti_dir / "poses" / "00.txt", "--diff-csv",
                            target], capsys)
    assert_one_line_error(code, err, "only with --diff")


def test_diff_figure_marks_exactly_the_differing_queries():
    from lidar_iris_eval.plotting.convention_diff import convention_diff_figure

    xy = np.c_[np.arange(20.0), np.zeros(20)]
    fig = convention_diff_figure(xy, np.zeros(20, bool), np.array([3, 4]), np.array([9]),
                                 ("a", "b"), ("x", "y"))
    lines = {line.get_gid(): line for line in fig.axes[0].get_lines()}
    assert list(lines["only:a"].get_xdata()) == [3.0, 4.0]
    assert list(lines["only:b"].get_xdata()) == [9.0]


def test_diff_with_a_changed_rule_gives_790(kitti_dir, capsys):
    code, out, err = run_cli(["gt", "--poses", kitti_dir / "poses" / "00.txt", "--diff",
                              "scancontext-eval", "scancontext-eval:radius=4", "--json"], capsys)
    assert code == 0, err
    d = json.loads(out)
    assert d["revisit_queries_scancontext-eval"] == 803
    assert d["revisit_queries_scancontext-eval:radius=4"] == 790
    assert (d["revisit_queries_only_a"], d["revisit_queries_only_b"]) == (13, 0)
    code, _, err = run_cli(["gt", "--poses", kitti_dir / "poses" / "00.txt", "--diff", "liris",
                            "logg3d:exclude=3"], capsys)
    assert_one_line_error(code, err, "no window in frames")


def test_diff_on_a_lidar_only_real_sequence_matches_gt(capsys):
    """LiDAR poses only, windows in seconds: the counts are still those of liris gt."""
    from conftest import SHARED

    d = SHARED / "data" / "real" / "hku-livox-avia-1"
    if not d.is_dir():
        pytest.skip("../shared/data/real/hku-livox-avia-1 is not available")
    seq = [d / "Scans", "--poses", d / "optimized_poses.txt", "--times", d / "times.txt",
           "--lidar-frame-poses"]
    counts = {}
    for name in ("liris", "logg3d"):
        code, out, err = run_cli(["gt", *seq, "--convention", name, "--json"], capsys)
        assert code == 0, err
        counts[name] = json.loads(out)
    code, out, err = run_cli(["gt", *seq, "--diff", "liris", "logg3d", "--json"], capsys)
    assert code == 0, err
    diff = json.loads(out)
    for key in ("revisit_queries", "positive_ordered_pairs"):
        assert diff[f"{key}_liris"] == counts["liris"][key]
        assert diff[f"{key}_logg3d"] == counts["logg3d"][key]
        assert diff[f"{key}_only_a"] - diff[f"{key}_only_b"] == \
            counts["liris"][key] - counts["logg3d"][key]
    code, out, _ = run_cli(["gt", *seq, "--explain", 160, 100, "--json"], capsys)
    rows = {r["convention"]: r for r in json.loads(out)["conventions"]}
    assert rows["liris"]["pose_frame"] == "lidar" and rows["liris"]["status"] != "unavailable"
    assert rows["logg3d"]["status"] != "unavailable"  # times are there
