"""Issue 35's bar: a simulated pose graph with 20 true and 3 planted false loops, written as
g2o (keyframe ids + SC-LIO-SAM-style keyframe times), TUM-style time pairs and a 1-based pair
list, scored from the poses alone (``liris eval --poses --times --loops``)."""

from __future__ import annotations

import json
from importlib.util import find_spec as _find_spec

import numpy as np
import pandas as pd
import pytest
from conftest import assert_one_line_error, run_cli

RADIUS, EXCLUDE, KEY_EVERY = 4.0, 30, 2
SIGMA_T, SIGMA_R = 0.05, 0.004  # odometry edge sigmas (m, rad) written in the g2o


def _quat(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()  # x y z w


def _pose_text(T: np.ndarray) -> str:
    return " ".join(f"{v:.9f}" for v in [*T[:3, 3], *_quat(T[:3, :3])])


def _info_text(sigma_t: float, sigma_r: float) -> str:
    info = np.diag([1 / sigma_t**2] * 3 + [4 / sigma_r**2] * 3)  # g2o: q_vec = angle / 2
    return " ".join(f"{v:.6g}" for v in info[np.triu_indices(6)])


def _yaw(a: float) -> np.ndarray:
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return T


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    from lidar_iris_eval.simulate.pipeline import build_scenario
    from lidar_iris_eval.simulate.presets import resolve_config

    root = tmp_path_factory.mktemp("acceptance")
    P = build_scenario(resolve_config("tiny-same", {"moving_cars": False})).poses  # LiDAR
    n = len(P)
    times = 1000.0 + 0.1 * np.arange(n)
    np.savetxt(root / "poses.txt", P[:, :3, :4].reshape(n, 12), fmt="%.9f")
    np.savetxt(root / "times.txt", times, fmt="%.3f")
    keys = np.arange(0, n, KEY_EVERY)  # keyframes: every 2nd scan, ids 0..K-1
    np.savetxt(root / "kf_times.txt", times[keys], fmt="%.3f")
    (root / "kf_map.txt").write_text("".join(f"{k} {s}\n" for k, s in enumerate(keys)))
    # independent ground truth: revisit queries i (i >= E) with some j <= i - E within R
    pos = P[:, :3, 3]
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    earlier = np.arange(n)[None, :] <= np.arange(n)[:, None] - EXCLUDE
    revisit = ((d < RADIUS) & earlier).any(axis=1)
    # 20 true loops between keyframes (query keyframe -> its nearest earlier keyframe)
    kd = d[np.ix_(keys, keys)]
    kearlier = keys[None, :] <= keys[:, None] - EXCLUDE
    candidates = [(a, int(np.argmin(np.where(kearlier[a], kd[a], np.inf))))
                  for a in range(len(keys)) if (np.where(kearlier[a], kd[a], np.inf) < 1.5).any()]
    assert len(candidates) >= 20
    pick = np.linspace(0, len(candidates) - 1, 20).round().astype(int)
    true_loops = [candidates[k] for k in pick]
    # 3 planted false loops: far apart (> 25 m), each claimed to be the same place
    rng = np.random.default_rng(5)
    false_loops = []
    while len(false_loops) < 3:
        a, b = sorted(rng.integers(0, len(keys), 2))[::-1]
        if kearlier[a, b] and kd[a, b] > 25 and a not in [q for q, _ in true_loops]:
            false_loops.append((int(a), int(b)))
    # drifting odometry: each step's motion with a yaw bias and noise
    K = len(keys)
    odo = [np.linalg.inv(P[keys[k]]) @ P[keys[k + 1]] for k in range(K - 1)]
    drift = [o @ _yaw(0.004 + rng.normal(0, 0.002)) for o in odo]
    for o in drift:
        o[:3, 3] += rng.normal(0, 0.02, 3)
    est = [P[keys[0]]]
    for o in drift:
        est.append(est[-1] @ o)
    lines = [f"VERTEX_SE3:QUAT {k} {_pose_text(T)}" for k, T in enumerate(est)] + ["FIX 0"]
    odo_info = _info_text(SIGMA_T, SIGMA_R)
    lines += [f"EDGE_SE3:QUAT {k} {k + 1} {_pose_text(o)} {odo_info}"
              for k, o in enumerate(drift)]
    loop_info = _info_text(0.1, 0.01)
    for a, b in true_loops:  # the pose of b in a's frame, from the ground truth
        lines.append(f"EDGE_SE3:QUAT {a} {b} {_pose_text(np.linalg.inv(P[keys[a]]) @ P[keys[b]])} "
                     f"{loop_info}")
    for a, b in false_loops:  # "the same place": a small offset, no rotation
        T = np.eye(4)
        T[0, 3] = 0.5
        lines.append(f"EDGE_SE3:QUAT {a} {b} {_pose_text(T)} {loop_info}")
    (root / "graph.g2o").write_text("\n".join(lines) + "\n")
    loops = true_loops + false_loops
    (root / "pairs.txt").write_text("".join(f"{keys[a] + 1} {keys[b] + 1}\n" for a, b in loops))
    (root / "loops.tum").write_text("# t_query t_match\n" + "".join(
        f"{times[keys[a]]:.3f} {times[keys[b]]:.3f}\n" for a, b in loops))
    # MapClosures: keyframe k as local map k (scans keys[k]..keys[k]+1, its frame the first)
    rel = {(a, b): np.linalg.inv(P[keys[a]]) @ P[keys[b]] for a, b in loops}
    (root / "mc").mkdir()
    (root / "mc" / "map_closures.txt").write_text("".join(
        f"{b} {a} {keys[b]} {keys[a]} " + " ".join(f"{v:.9g}" for v in rel[a, b].ravel()) + "\n"
        for a, b in loops))
    (root / "closures18.txt").write_text("".join(
        f"{b} {a} " + " ".join(f"{v:.9g}" for v in rel[a, b].ravel()) + "\n"
        for a, b in loops))
    (root / "maps.txt").write_text("# map first_scan last_scan\n" + "".join(
        f"{k} {s} {s + KEY_EVERY - 1}\n" for k, s in enumerate(keys)))
    # per-scan drifting odometry (KITTI file) + a posed pair list of the same loops, by scan
    steps = [np.linalg.inv(P[k]) @ P[k + 1] @ _yaw(0.002 + rng.normal(0, 0.001))
             for k in range(n - 1)]
    odo_scan = [P[0]]
    for o in steps:
        odo_scan.append(odo_scan[-1] @ o)
    odo_scan = np.array(odo_scan)
    np.savetxt(root / "odometry.txt", odo_scan[:, :3, :4].reshape(n, 12), fmt="%.9f")
    offset = np.eye(4)
    offset[0, 3] = 0.5
    (root / "posed_pairs.txt").write_text("".join(
        f"{keys[a]} {keys[b]} 0 " + _pose_text(rel[a, b] if (a, b) in true_loops else offset)
        + "\n" for a, b in loops))
    covered = np.zeros(n, dtype=bool)
    covered[[keys[a] for a, _ in true_loops]] = True
    expected = {"coverage": np.count_nonzero(covered & revisit) / np.count_nonzero(revisit),
                "n_revisits": int(np.count_nonzero(revisit)), "revisit": revisit,
                "true_queries": [int(keys[a]) for a, _ in true_loops],
                "false_scans": [(int(keys[a]), int(keys[b])) for a, b in false_loops]}
    return root, expected


def _eval(root, out, capsys, *args):
    code, stdout, err = run_cli(["eval", "--poses", root / "poses.txt", "--times",
                                 root / "times.txt", "--radius", str(RADIUS), "--exclude",
                                 str(EXCLUDE), "--pose-frame", "lidar", "--out", out, *args],
                                capsys)
    assert code == 0, err
    return json.loads((out / "metrics.json").read_text())["results"], stdout + err


@pytest.mark.parametrize("name, args", [
    ("g2o", ["--loops-times", "kf_times.txt"]),
    ("g2o", ["--loops-map", "kf_map.txt"]),
    ("tum", []),
    ("pairs", ["--loops-index-base", "1"]),
    ("mapclosures", []),
    ("mapclosures18", ["--loops-map", "maps.txt"]),
])
def test_each_format_gives_20_tp_3_fp_and_the_coverage(world, tmp_path, capsys, name, args):
    root, expected = world
    file = {"g2o": "graph.g2o", "tum": "loops.tum", "pairs": "pairs.txt",
            "mapclosures": "mc/map_closures.txt", "mapclosures18": "closures18.txt"}[name]
    args = [a if not a.endswith(".txt") else str(root / a) for a in args]
    rows, text = _eval(root, tmp_path / "run", capsys, "--loops", root / file, "--no-posegraph",
                       *args)
    row = rows[0]
    assert (row["loops_tp"], row["loops_fp"]) == (20, 3)
    assert row["n_revisits"] == expected["n_revisits"]
    assert row["revisit_coverage"] == pytest.approx(expected["coverage"], abs=1e-12)
    table = pd.read_csv(tmp_path / "run" / "loops" / f"loops:{root.joinpath(file).stem}"
                        / "loops.csv", dtype={"status": str})
    false = sorted(zip(table[table.status == "false"]["query"],
                       table[table.status == "false"]["match"], strict=True))
    assert false == sorted(expected["false_scans"])
    assert "20 TP / 3 FP" in text
    if name in ("g2o", "mapclosures", "mapclosures18"):  # the loops' poses: exact for true loops
        assert row["loops_rte_m_median"] < 1e-6 and row["loops_rre_deg_median"] < 1e-4
        assert row["loops_rr"] == 1.0


def test_without_gtsam_one_warning_or_one_error(world, tmp_path, capsys, monkeypatch):
    import sys

    root, _ = world
    monkeypatch.setitem(sys.modules, "gtsam", None)  # import gtsam now fails
    monkeypatch.setattr("importlib.util.find_spec",
                        lambda name, *a: None if name == "gtsam" else _find_spec(name, *a))
    rows, text = _eval(root, tmp_path / "a", capsys, "--loops", root / "graph.g2o",
                       "--loops-times", root / "kf_times.txt")
    assert "posegraph_ape_true_m" not in rows[0] and "gtsam is not installed" in text
    code, _, err = run_cli(["eval", "--poses", root / "poses.txt", "--times", root / "times.txt",
                            "--loops", root / "graph.g2o", "--loops-times",
                            root / "kf_times.txt", "--posegraph", "--out", tmp_path / "b"],
                           capsys)
    assert_one_line_error(code, err, "needs gtsam", "posegraph")


def test_coverage_within_a_frame_tolerance_and_stretches(world, tmp_path, capsys):
    root, expected = world
    revisit, queries, tol = expected["revisit"], expected["true_queries"], 3
    near = np.array([any(abs(f - q) <= tol for q in queries) for f in range(len(revisit))])
    stretches, start = [], None  # maximal runs of revisit frames, by a plain loop
    for f, r in enumerate([*revisit, False]):
        if r and start is None:
            start = f
        if not r and start is not None:
            stretches.append((start, f - 1))
            start = None
    touched = sum(near[a:b + 1].any() for a, b in stretches)
    rows, _ = _eval(root, tmp_path / "run", capsys, "--loops", root / "pairs.txt",
                    "--loops-index-base", "1", "--loops-coverage-tolerance", str(tol))
    row = rows[0]
    assert row["revisit_coverage"] == pytest.approx(
        np.count_nonzero(near & revisit) / np.count_nonzero(revisit), abs=1e-12)
    assert row["revisit_coverage"] > expected["coverage"]
    assert (row["n_revisit_stretches"], row["n_revisit_stretches_covered"]) == \
        (len(stretches), touched)
    print("coverage tol 3:", row["revisit_coverage"], "stretches", touched, "of",
          len(stretches))


#: APE RMSE (m) measured on this graph (gtsam 4.2, LM, no kernel): none / true only / all
PINNED = {"none": 1.2752, "true": 0.0691, "all": 8.6150}


def _kabsch_ape(est: np.ndarray, ref: np.ndarray) -> float:
    """APE RMSE after a rigid alignment, by scipy's Kabsch (independent of liris's Umeyama)."""
    from scipy.spatial.transform import Rotation

    e, r = est - est.mean(axis=0), ref - ref.mean(axis=0)
    R, _ = Rotation.align_vectors(r, e)
    return float(np.sqrt(np.mean(np.sum((r - R.apply(e)) ** 2, axis=1))))


def test_posegraph_damage_true_loops_beat_none_and_all(world, tmp_path, capsys):
    pytest.importorskip("gtsam")
    root, _ = world
    rows, text = _eval(root, tmp_path / "run", capsys, "--loops", root / "graph.g2o",
                       "--loops-times", root / "kf_times.txt")
    row = rows[0]
    none, true, every = (row[f"posegraph_ape_{k}_m"] for k in ("none", "true", "all"))
    print("APE none/true/all", none, true, every, row["posegraph_worst_false_added_m"])
    assert true < none and true < every
    for key, value in (("none", none), ("true", true), ("all", every)):
        assert value == pytest.approx(PINNED[key], rel=0.02), key
    # odometry alone leaves the drifted chain as it is: its APE from the file's vertices
    from lidar_iris_eval.io.loops import parse_g2o

    graph = parse_g2o(root / "graph.g2o")
    est = np.array([graph.vertices[k][:3, 3] for k in sorted(graph.vertices)])
    ref = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)[::KEY_EVERY, :, 3]
    assert none == pytest.approx(_kabsch_ape(est, ref), rel=1e-4)
    table = pd.read_csv(tmp_path / "run" / "loops" / "loops:graph" / "posegraph.csv")
    singles = table[table.graph.str.startswith("true+")]
    assert len(singles) == 3 and (singles.added_m > 0).all()
    assert "APE RMSE" in text
    code, shown, err = run_cli(["show", tmp_path / "run"], capsys)
    assert code == 0, err
    assert "ape_true_m" in shown and f"{true:.4f}" in shown


#: APE RMSE (m) of the --loops-odometry graph (per-scan drift, equal edge weights)
PINNED_ODOMETRY = {"none": 1.4043, "true": 0.01611, "all": 11.012}


def test_posegraph_from_an_odometry_and_posed_pairs(world, tmp_path, capsys):
    pytest.importorskip("gtsam")
    root, _ = world
    rows, text = _eval(root, tmp_path / "run", capsys, "--loops", root / "posed_pairs.txt",
                       "--loops-odometry", root / "odometry.txt")
    row = rows[0]
    assert (row["loops_tp"], row["loops_fp"]) == (20, 3)
    none, true, every = (row[f"posegraph_ape_{k}_m"] for k in ("none", "true", "all"))
    print("odometry graph APE none/true/all", none, true, every)
    assert true < none and true < every
    P = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)[:, :, 3]
    odo = np.loadtxt(root / "odometry.txt").reshape(-1, 3, 4)[:, :, 3]
    assert none == pytest.approx(_kabsch_ape(odo, P), rel=1e-4)
    for key, value in (("none", none), ("true", true), ("all", every)):
        assert value == pytest.approx(PINNED_ODOMETRY[key], rel=0.02), key


def test_robust_kernel_limits_the_damage(world, tmp_path, capsys):
    pytest.importorskip("gtsam")
    root, _ = world
    rows, _ = _eval(root, tmp_path / "run", capsys, "--loops", root / "graph.g2o",
                    "--loops-times", root / "kf_times.txt", "--posegraph-kernel", "cauchy")
    row = rows[0]
    print("cauchy APE none/true/all", row["posegraph_ape_none_m"], row["posegraph_ape_true_m"],
          row["posegraph_ape_all_m"])
    assert row["posegraph_kernel"] == "cauchy"
    assert row["posegraph_ape_all_m"] < PINNED["all"]


def test_unplaceable_keyframe_and_time(world, tmp_path, capsys):
    root, _ = world
    short = tmp_path / "short_times.txt"
    short.write_text("".join(f"{t}\n" for t in np.loadtxt(root / "kf_times.txt")[:50]))
    code, _, err = run_cli(["eval", "--poses", root / "poses.txt", "--times", root / "times.txt",
                            "--loops", root / "graph.g2o", "--loops-times", short, "--out",
                            tmp_path / "a"], capsys)
    assert_one_line_error(code, err, "graph.g2o:", "has no time in")
    bad = tmp_path / "late.tum"
    bad.write_text("1010.0 1001.0\n5000.0 1001.0\n")
    code, _, err = run_cli(["eval", "--poses", root / "poses.txt", "--times", root / "times.txt",
                            "--loops", bad, "--out", tmp_path / "b"], capsys)
    assert_one_line_error(code, err, "late.tum:2", "matches no scan")


def _by_gid(fig, gid):
    for ax in fig.axes:
        for artist in [*ax.collections, *ax.patches, *ax.lines]:
            if artist.get_gid() == gid:
                yield artist


def test_figures_draw_each_loop_and_the_ape_bars(world, tmp_path, capsys):
    pytest.importorskip("gtsam")
    from lidar_iris_eval.plotting.figures import build_loops
    from lidar_iris_eval.runs.reader import load_run

    root, expected = world
    out = tmp_path / "run"
    _eval(root, out, capsys, "--loops", root / "graph.g2o", "--loops-times",
          root / "kf_times.txt")
    trajectory, bars = build_loops(load_run(out))
    P = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)[:, :2, 3]  # LiDAR frame: x, y
    (true,) = _by_gid(trajectory, "loops-true:loops:graph")
    (false,) = _by_gid(trajectory, "loops-false:loops:graph")
    assert len(true.get_segments()) == 20
    drawn = sorted(tuple(np.round(s.ravel(), 6)) for s in false.get_segments())
    wanted = sorted(tuple(np.round(np.r_[P[q], P[m]], 6)) for q, m in expected["false_scans"])
    assert drawn == wanted
    heights = [p.get_height() for p in _by_gid(bars, "ape:loops:graph")]
    table = pd.read_csv(out / "loops" / "loops:graph" / "posegraph.csv")
    assert heights == pytest.approx(table.ape_rmse_m[:3].tolist())
    assert len(list(_by_gid(bars, "added:loops:graph"))) == 3
    code, stdout, err = run_cli(["plot", out], capsys)
    assert code == 0, err
    assert (out / "figures" / "loops_trajectory.png").is_file()
    assert (out / "figures" / "posegraph_ape.png").is_file()
    pytest.importorskip("plotly")
    code, _, err = run_cli(["report", out], capsys)
    assert code == 0, err
    assert "id='loops'" in (out / "report" / "index.html").read_text()


def test_config_reruns_a_loops_run_from_poses(world, tmp_path, capsys):
    root, _ = world
    rows, _ = _eval(root, tmp_path / "a", capsys, "--loops", root / "graph.g2o", "--loops-times",
                    root / "kf_times.txt", "--no-posegraph", "--loops-coverage-tolerance", "2")
    code, _, err = run_cli(["eval", "--config", tmp_path / "a", "--out", tmp_path / "b"], capsys)
    assert code == 0, err
    again = json.loads((tmp_path / "b" / "metrics.json").read_text())["results"]
    keys = ("loops_tp", "loops_fp", "revisit_coverage", "coverage_tolerance_frames", "ap")
    assert [{k: r[k] for k in keys} for r in again] == [{k: r[k] for k in keys} for r in rows]


def test_g2o_information_means_the_same_error_in_gtsam():
    gtsam = pytest.importorskip("gtsam")
    from scipy.spatial.transform import Rotation

    from lidar_iris_eval.evaluation.posegraph_damage import _gtsam_information

    rng = np.random.default_rng(2)
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 6 * np.eye(6)  # g2o order: x y z qx qy qz
    measured = np.eye(4)
    measured[:3, :3] = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()
    measured[:3, 3] = [1.0, 2.0, -0.5]
    delta = np.eye(4)  # a small error: measured^-1 * (Xa^-1 Xb)
    delta[:3, :3] = Rotation.from_rotvec([0.002, -0.001, 0.003]).as_matrix()
    delta[:3, 3] = [0.003, -0.002, 0.001]
    Xb = measured @ delta
    # g2o's error: the translation and the quaternion's vector part of delta
    e = np.r_[delta[:3, 3], Rotation.from_matrix(delta[:3, :3]).as_quat()[:3]]
    g2o_chi2 = e @ info @ e
    factor = gtsam.BetweenFactorPose3(0, 1, gtsam.Pose3(measured),
                                      gtsam.noiseModel.Gaussian.Information(
                                          _gtsam_information(info)))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose3(np.eye(4)))
    values.insert(1, gtsam.Pose3(Xb))
    assert 2 * factor.error(values) == pytest.approx(g2o_chi2, rel=0.01)


def test_tum_poses_bring_their_own_times(world, tmp_path, capsys):
    from scipy.spatial.transform import Rotation

    root, _ = world
    P = np.loadtxt(root / "poses.txt").reshape(-1, 3, 4)
    times = np.loadtxt(root / "times.txt")
    quats = Rotation.from_matrix(P[:, :, :3]).as_quat()
    tum = tmp_path / "poses.tum.txt"
    np.savetxt(tum, np.c_[times, P[:, :, 3], quats], fmt="%.9f")
    code, _, err = run_cli(["eval", "--poses", tum, "--radius", str(RADIUS), "--exclude",
                            str(EXCLUDE), "--loops", root / "loops.tum", "--out",
                            tmp_path / "run"], capsys)
    assert code == 0, err
    row = json.loads((tmp_path / "run" / "metrics.json").read_text())["results"][0]
    assert (row["loops_tp"], row["loops_fp"]) == (20, 3)
