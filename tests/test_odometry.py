"""--odometry gt|kiss-icp: drift figures, the flag, the missing extra, no ground-truth leakage.

Tests marked ``kiss`` need the optional extra ``odometry`` (kiss-icp) and skip
without it; CI runs them in its second venv (.ci/run).
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.drift import ate_rmse, drift_report, relative_translation_error
from lidar_iris_eval.matching.geometry import yaw_pose

try:
    import kiss_icp.kiss_icp  # noqa: F401

    HAVE_KISS = True
except ImportError:
    HAVE_KISS = False

kiss = pytest.mark.skipif(not HAVE_KISS, reason='needs the "odometry" extra (kiss-icp)')


def _line(n: int, step: float = 1.0) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, 0, 3] = np.arange(n) * step
    return poses


# ---------------------------------------------------------------------- drift figures

def test_a_rigidly_moved_trajectory_has_no_drift():
    gt = _line(201)
    gt[:, 1, 3] = np.sin(np.arange(201) / 20.0) * 5.0  # not collinear: the alignment is unique
    T = yaw_pose(40.0, (3.0, -7.0, 1.0))
    est = T @ gt
    assert ate_rmse(est, gt) == pytest.approx(0.0, abs=1e-9)
    assert relative_translation_error(est, gt, 100.0) == pytest.approx(0.0, abs=1e-9)


def test_a_one_percent_scale_error_by_hand():
    # x_i = i (201 frames, 200 m) against 1.01 i: every 100 m segment is 101 m long, 1 %;
    # the best rigid alignment centres both lines, residuals 0.01 (i - 100), so the RMSE
    # is 0.01 * sqrt((201^2 - 1) / 12) = 0.58023 m
    gt = _line(201)
    est = _line(201, 1.01)
    assert relative_translation_error(est, gt, 100.0) == pytest.approx(1.0, rel=1e-9)
    assert ate_rmse(est, gt) == pytest.approx(0.01 * np.sqrt((201**2 - 1) / 12), rel=1e-6)
    report = drift_report(est, gt, (50.0, 100.0, 500.0))
    assert report["path_m"] == pytest.approx(200.0)
    assert report["rte_pct_50m"] == pytest.approx(1.0)
    assert report["rte_pct_500m"] is None  # no segment that long: undefined, not 0


def test_a_heading_error_shows_in_the_relative_error():
    # the estimate turns 1 degree at frame 0: every later step is rotated by 1 degree, so
    # a 100 m segment ends 2 sin(0.5 deg) * 100 m = 1.745 m away, 1.745 %
    gt = _line(301)
    est = yaw_pose(1.0, (0.0, 0.0, 0.0)) @ gt
    est[0] = gt[0]
    rte = relative_translation_error(est, gt, 100.0)
    # segments from frame 0 see the turn; the others are only rotated copies (0 %)
    expected = 2 * np.sin(np.radians(0.5)) * 100 / 100 * 100 / 201
    assert rte == pytest.approx(expected, rel=1e-6)


# ---------------------------------------------------------------------- the flag

def _sequence(root: Path, frames: int = 30) -> Path:
    from lidar_iris_eval.simulate.pipeline import simulate_sequence

    return simulate_sequence(root, "tiny-mixed", frames=frames, azimuth_steps=512)


@pytest.fixture(scope="module")
def short_sequence(tmp_path_factory) -> Path:
    return _sequence(tmp_path_factory.mktemp("odometry") / "seq")


def test_missing_extra_is_one_error_line(short_sequence, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "kiss_icp", None)
    monkeypatch.setitem(sys.modules, "kiss_icp.kiss_icp", None)
    for verb in (["extract", short_sequence], ["eval", short_sequence, "--protocol", "1"]):
        code, _, err = run_cli([*verb, "-d", "esm", "--odometry", "kiss-icp", "-q",
                                "--cache-dir", tmp_path / "cache", "--out", tmp_path / "run"]
                               if verb[0] == "eval" else
                               [*verb, "-d", "esm", "--odometry", "kiss-icp", "-q",
                                "--cache-dir", tmp_path / "cache"], capsys)
        assert_one_line_error(code, err, "--odometry kiss-icp", 'extra "odometry"')


def test_unknown_odometry_and_the_old_param_are_one_error_line(short_sequence, tmp_path,
                                                               capsys):
    code, _, err = run_cli(["eval", short_sequence, "-d", "esm", "--protocol", "1",
                            "--odometry", "slam", "--out", tmp_path / "run"], capsys)
    assert_one_line_error(code, err, "--odometry slam", "kiss-icp")
    code, _, err = run_cli(["eval", short_sequence, "-d", "esm", "--protocol", "1",
                            "--param", "esm.odometry=kiss-icp", "--out", tmp_path / "run"],
                           capsys)
    assert_one_line_error(code, err, "--param esm.odometry", "--odometry")
    # a pose file is the .g2o vertices only: refused for a method that builds local maps
    poses = tmp_path / "poses.txt"
    shutil.copy(short_sequence / "poses.txt", poses)
    code, _, err = run_cli(["eval", short_sequence, "-d", "esm", "--protocol", "1",
                            "--odometry", poses, "--out", tmp_path / "run"], capsys)
    assert_one_line_error(code, err, f"--odometry {poses}", "esm")


def test_the_flag_reaches_the_descriptor_and_the_cache_key(short_sequence):
    from lidar_iris_eval.cli.descriptor_options import build_descriptors
    from lidar_iris_eval.extract import cache_key
    from lidar_iris_eval.io import open_sequence

    seq = open_sequence(short_sequence)
    (esm_gt,) = build_descriptors("esm", None, "hdl64", (), "gt")
    (iris,) = build_descriptors("lidar-iris", None, "hdl64", (), "kiss-icp" if HAVE_KISS
                                else "gt")
    assert esm_gt.local_map_settings().odometry == "gt"
    assert not hasattr(iris.params, "odometry")  # a method without local maps: as it was
    if HAVE_KISS:
        (esm_kiss,) = build_descriptors("esm", None, "hdl64", (), "kiss-icp")
        assert esm_kiss.local_map_settings().odometry == "kiss-icp"
        assert cache_key(seq, esm_gt) != cache_key(seq, esm_kiss)


def _perturbed_copy(src: Path, dst: Path) -> Path:
    """The same scans (copied with their times: the same fingerprint), other GT poses."""
    shutil.copytree(src, dst)
    rows = np.loadtxt(src / "poses.txt").reshape(-1, 3, 4)
    rng = np.random.default_rng(7)
    out = []
    for row in rows:
        P = np.vstack([row, [0, 0, 0, 1]])
        noise = yaw_pose(rng.uniform(-10, 10), rng.uniform(-2, 2, 3))
        out.append((P @ noise)[:3].ravel())
    np.savetxt(dst / "poses.txt", np.array(out), fmt="%.9e")
    return dst


def _features(seq_dir: Path, odometry: str, workers: int = 1, chunk_size: int = 50):
    from lidar_iris_eval.cli.descriptor_options import build_descriptors
    from lidar_iris_eval.extract import cache_key, extract
    from lidar_iris_eval.io import open_sequence

    seq = open_sequence(seq_dir)
    (esm,) = build_descriptors("esm", None, "hdl64", ("esm.window=5",), odometry)
    db = extract(seq, esm, workers=workers, chunk_size=chunk_size)
    values = {k: np.asarray(v) for k, v in db.descriptors.values.items() if k != "odometry_s"}
    return values, cache_key(seq, esm), seq


def test_gt_odometry_features_follow_the_gt_poses(short_sequence, tmp_path):
    """The control of the leakage test below: with gt, perturbed poses change the features
    and the cache key (the test below could fail)."""
    other = _perturbed_copy(short_sequence, tmp_path / "perturbed")
    a, key_a, _ = _features(short_sequence, "gt")
    b, key_b, _ = _features(other, "gt")
    assert key_a != key_b
    assert not np.array_equal(a["world"], b["world"])


@kiss
def test_kiss_icp_features_do_not_depend_on_the_gt_poses(short_sequence, tmp_path):
    other = _perturbed_copy(short_sequence, tmp_path / "perturbed")
    a, key_a, seq_a = _features(short_sequence, "kiss-icp")
    b, key_b, seq_b = _features(other, "kiss-icp")
    assert not np.allclose(seq_a.poses, seq_b.poses, atol=0.1)  # the GT did change
    assert key_a == key_b
    assert a.keys() == b.keys() and {"world", "pose", "centroids", "embedding"} <= set(a)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    # chunks in a process pool see the poses of the one KISS-ICP run over the sequence
    # (only the poses: ESM's segment tracking restarts per chunk, so embeddings may differ)
    c, _, _ = _features(short_sequence, "kiss-icp", workers=2, chunk_size=10)
    np.testing.assert_array_equal(a["pose"], c["pose"])


@kiss
def test_kiss_icp_recovers_a_short_simulated_trajectory(short_sequence):
    """KISS-ICP on 30 simulated scans (512 azimuth steps, about 1 m apart): after
    expressing the ground truth in the first scan's frame (KISS-ICP's world), every
    position within 0.5 m (the second scan, registered against a one-scan map with no
    motion prior, is the worst: 0.41 m measured), the median within 0.15 m, and every
    heading within 1 degree."""
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.localmaps.odometry import estimate_odometry

    seq = open_sequence(short_sequence)
    run = estimate_odometry(seq, "kiss-icp")
    gt = np.linalg.inv(seq.poses[0]) @ seq.poses
    np.testing.assert_allclose(run.poses[0], np.eye(4), atol=1e-12)
    position = np.linalg.norm(run.poses[:, :3, 3] - gt[:, :3, 3], axis=1)
    rel = np.linalg.inv(gt[:, :3, :3]) @ run.poses[:, :3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    travelled = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1).sum()
    assert travelled > 10.0  # it moved
    assert position.max() < 0.5, position.max()
    assert np.median(position) < 0.15, np.median(position)
    assert angle.max() < 1.0, angle.max()
    assert (run.seconds > 0).all() and run.version


@kiss
def test_eval_records_kiss_icp_in_metrics_and_config(short_sequence, tmp_path, capsys):
    import yaml

    out = tmp_path / "run"
    code, _, err = run_cli(["eval", short_sequence, "-d", "esm", "--protocol", "1",
                            "--exclude", "10", "--odometry", "kiss-icp", "-q",
                            "--cache-dir", tmp_path / "cache", "--out", out], capsys)
    assert code == 0, err
    metrics = json.loads((out / "metrics.json").read_text())
    row = next(r for r in metrics["results"] if r["descriptor"] == "esm")
    assert row["odometry"] == "kiss-icp"
    assert row["odometry_ms_per_scan"] > 0
    assert metrics["conventions"]["odometry"] == "kiss-icp"
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["odometry"] == "kiss-icp"
    assert config["descriptors"][0]["params"]["odometry"] == "kiss-icp"
    from lidar_iris_eval.runs.replay import config_defaults, read_config

    defaults = config_defaults(read_config(out))
    assert defaults["odometry_text"] == "kiss-icp"
    assert not any(p.startswith("esm.odometry") for p in defaults["params"])


def test_check_odometry_names_the_flag():
    from lidar_iris_eval.localmaps.odometry import check_odometry

    assert check_odometry("gt") == "gt"
    with pytest.raises(LirisError, match="--odometry slam"):
        check_odometry("slam")


def _local_map_features(world_from: np.ndarray) -> list[dict]:
    """Feature sets of 4 local maps, the world changed by ``world_from`` (4x4): frame 0
    sees 30 segments, frames 1 and 2 others 200 m away, query frame 3 sees frame 0's
    segments again from a pose 1.5 m and 20 degrees away."""
    rng = np.random.default_rng(3)
    seen = rng.uniform(-25, 25, (30, 3)) * [1, 1, 0.1]
    emb = rng.normal(size=(30, 16)).astype(np.float32)
    poses = [yaw_pose(0.0, (0, 0, 0)), yaw_pose(90.0, (200, 0, 0)),
             yaw_pose(90.0, (200, 30, 0)), yaw_pose(20.0, (1.5, 0.5, 0))]
    frames = []
    for f, P in enumerate(poses):
        if f in (1, 2):
            world = seen + [200.0, 15.0 * f, 0.0]
            e = rng.normal(size=(30, 16)).astype(np.float32)
        else:
            world, e = seen, emb + (0.001 if f == 3 else 0.0)
        Pw = world_from @ P
        ww = world @ world_from[:3, :3].T + world_from[:3, 3]
        inv = np.linalg.inv(Pw)
        frames.append({"embedding": e.astype(np.float32), "quality": np.ones(30),
                       "centroids": ww @ inv[:3, :3].T + inv[:3, 3], "world": ww,
                       "sizes": np.full(30, 200, np.int64), "pose": Pw.reshape(1, 4, 4)})
    return frames


def test_loop_poses_are_relative_whatever_the_odometry_world_frame():
    """The pose ESM reports (database LiDAR frame -> query LiDAR frame) is the same when
    the odometry's world frame moves (KISS-ICP's is the first scan's), and equals
    inv(P_query) P_database."""
    import dataclasses

    from lidar_iris_eval.descriptors import get_descriptor

    base = get_descriptor("esm")
    esm = type(base)(dataclasses.replace(base.params, window=1, min_target=10), base.preset)
    poses = []
    for world_from in (np.eye(4), yaw_pose(-70.0, (500.0, -300.0, 12.0))):
        feats = _local_map_features(world_from)
        db = esm.prepare(feats)
        frames, _ = esm.retrieve(db, 3, 3, 1)
        assert list(frames) == [0]
        poses.append(esm.verify(db, 3, frames).pose[0])
    truth = np.linalg.inv(yaw_pose(20.0, (1.5, 0.5, 0))) @ np.eye(4)
    np.testing.assert_allclose(poses[0], truth, atol=1e-6)
    np.testing.assert_allclose(poses[1], poses[0], atol=1e-6)
