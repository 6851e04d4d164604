"""``liris extract`` / ``liris eval`` end to end: the run-folder contract and bad input."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import assert_one_line_error, run_cli
from test_protocols import two_pass_sequence

from lidar_iris_eval import __version__
from lidar_iris_eval.descriptors import _REGISTRY
from lidar_iris_eval.io import open_sequence

TOYS = {
    "toy": "test_protocols:ToyHist",
    "toy-asym": "test_protocols:ToyAsym",
    "toy-retrieval": "test_protocols:ToyRetrieval",
}


@pytest.fixture(autouse=True)
def toys(monkeypatch):
    for name, target in TOYS.items():
        monkeypatch.setitem(_REGISTRY, name, target)


@pytest.fixture
def seq_dir(tmp_path):
    return two_pass_sequence(tmp_path / "seq", n_per_pass=12)


def eval_args(seq_dir, tmp_path, *extra):
    return ["eval", seq_dir, "--protocol", "1", "--protocol", "2", "-d", "toy,toy-asym",
            "--exclude", "5", "--cache-dir", tmp_path / "cache", "--out", tmp_path / "run",
            "-q", *extra]


def test_eval_writes_the_documented_run_folder(seq_dir, tmp_path, capsys):
    code, out, err = run_cli(eval_args(seq_dir, tmp_path), capsys)
    assert code == 0, err
    run_dir = tmp_path / "run"
    n = 24
    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert config["version"] == __version__
    assert config["sequence"]["path"] == str(seq_dir.resolve())
    assert [d["name"] for d in config["descriptors"]] == ["toy", "toy-asym"]
    assert config["descriptors"][0]["params"] == {"bins": 16, "max_range": 20.0, "delay": 0.0}
    assert config["protocols"] == [1, 2]
    conv = config["convention"]  # the conventions, stored once (issue 39 D2)
    assert (conv["exclude"], conv["exclude_seconds"], conv["preset"]) == (5, None, "custom")
    assert (conv["radius"], conv["distance"], conv["pose_frame"]) == (4.0, "3d", "camera")
    assert conv["recall_denominator"] == "revisits" and config["candidates"] is None
    assert config["pose_frame"] == "camera"  # the frame used

    metrics = json.loads((run_dir / "metrics.json").read_text())
    assert metrics["version"] == __version__
    assert metrics["conventions"]["recall_denominator"] == "revisits"
    rows = {(r["protocol"], r["descriptor"]): r for r in metrics["results"]}
    assert set(rows) == {(1, "toy"), (2, "toy"), (1, "toy-asym"), (2, "toy-asym")}
    common = {"preset", "ap", "f1_max", "f1_threshold", "r100p", "ep", "n_positives",
              "extract_ms_per_scan"}
    for (protocol, _), row in rows.items():
        assert common <= set(row)
        if protocol == 1:
            assert {"n_queries", "n_revisits", "match_ms_per_query"} <= set(row)
            assert (row["n_queries"], row["n_revisits"], row["f1_max"]) == (19, 12, 1.0)
        else:
            assert {"n_pairs", "match_us_per_pair"} <= set(row)
            assert (row["n_pairs"], row["n_positives"], row["ap"]) == (n * (n - 1), 24, 1.0)
    table = pd.read_csv(run_dir / "metrics.csv")
    assert len(table) == 4 and {"protocol", "descriptor", "ap"} <= set(table.columns)

    matches = pd.read_csv(run_dir / "protocol1" / "toy" / "matches.csv")
    assert list(matches.columns[:7]) == ["query", "match", "distance", "yaw_deg",
                                         "match_dist_m", "is_revisit", "is_true"]
    assert matches["query"].tolist() == list(range(5, n))
    second = matches[matches["query"] >= 12]
    assert (second["match"] == second["query"] - 12).all() and (second["distance"] == 0).all()
    for protocol in (1, 2):
        pr = pd.read_csv(run_dir / f"protocol{protocol}" / "toy-asym" / "pr.csv")
        assert list(pr.columns[:3]) == ["threshold", "precision", "recall"]
        assert pr["threshold"].is_monotonic_increasing
    aff = np.load(run_dir / "protocol2" / "toy" / "affinity.npy")
    assert aff.shape == (n, n) and aff.dtype == np.float32
    assert np.isnan(np.diag(aff)).all() and np.array_equal(aff, aff.T, equal_nan=True)
    timing = pd.read_csv(run_dir / "timing" / "toy.csv")
    assert timing["scan"].tolist() == list(range(n)) and (timing["extract_s"] > 0).all()
    seq = open_sequence(seq_dir)
    np.testing.assert_array_equal(np.load(run_dir / "positions.npy"), seq.positions("camera"))
    np.testing.assert_array_equal(np.load(run_dir / "poses.npy"), seq.camera_poses)
    assert "toy-asym" in out and "results in" in out
    assert not list(tmp_path.glob(".run.tmp-*"))


def test_existing_run_needs_overwrite(seq_dir, tmp_path, capsys):
    assert run_cli(eval_args(seq_dir, tmp_path), capsys)[0] == 0
    marker = tmp_path / "run" / "metrics.json"
    before = marker.read_text()
    code, _, err = run_cli(eval_args(seq_dir, tmp_path), capsys)
    assert_one_line_error(code, err, str(tmp_path / "run"), "--overwrite")
    assert marker.read_text() == before
    code, _, err = run_cli(eval_args(seq_dir, tmp_path, "--overwrite", "--recall-denominator",
                                 "accepted"), capsys)
    assert code == 0, err
    config = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert config["convention"]["recall_denominator"] == "accepted"
    assert not list(tmp_path.glob(".run.*"))  # no temporary or old folders left


@pytest.mark.parametrize(("args", "fragments"), [
    (["-d", "nope"], ["--descriptor nope", "unknown descriptor"]),
    (["-d", "toy", "--candidates", "3"], ["--candidates 3", "toy has no retrieval"]),
    (["-d", "toy", "--exclude", "soon"], ["--exclude soon"]),
    (["-d", "m2dp", "--preset", "nonexistent"], ["--preset nonexistent"]),
])
def test_bad_input_is_one_line_exit_2(seq_dir, tmp_path, capsys, args, fragments):
    code, _, err = run_cli(["eval", seq_dir, "--protocol", "1", "--out", tmp_path / "r",
                        "--cache-dir", tmp_path / "c", *args], capsys)
    assert_one_line_error(code, err, *fragments)
    assert not (tmp_path / "r").exists()


def test_missing_sequence_is_one_line_exit_2(tmp_path, capsys):
    for command in (["eval", "--protocol", "1"], ["extract"]):
        args = [command[0], tmp_path / "missing", *command[1:], "-d", "toy"]
        code, _, err = run_cli(args, capsys)
        assert_one_line_error(code, err, str(tmp_path / "missing"), "no such file")


def test_candidates_run_uses_the_descriptor_retrieval(seq_dir, tmp_path, capsys):
    code, _, err = run_cli(["eval", seq_dir, "--protocol", "1", "-d", "toy-retrieval",
                        "--candidates", "2", "--exclude", "5", "--out", tmp_path / "r",
                        "--cache-dir", tmp_path / "c", "-q", "--json"], capsys)
    assert code == 0, err
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    (row,) = metrics["results"]
    assert row["match_source"] == "candidates:2" and row["n_queries"] == 19
    assert yaml.safe_load((tmp_path / "r" / "config.yaml").read_text())["candidates"] == 2


def test_extract_then_eval_reuses_the_cache(seq_dir, tmp_path, capsys):
    cache = tmp_path / "cache"
    code, out, err = run_cli(["extract", seq_dir, "-d", "toy", "--cache-dir", cache, "-q",
                          "--json"], capsys)
    assert code == 0, err
    first = json.loads(out)["results"][0]
    assert first["from_cache"] is False and first["scans"] == 24
    code, out, _ = run_cli(["extract", seq_dir, "-d", "toy", "--cache-dir", cache, "-q", "--json"],
                       capsys)
    assert json.loads(out)["results"][0]["from_cache"] is True
    assert len(list(cache.glob("*.npz"))) == 1


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """A simulated tiny sequence when the simulator is there, else a random walk."""
    tmp_path = tmp_path_factory.mktemp("simulated")
    try:
        from lidar_iris_eval.simulate import simulate_sequence
    except ImportError:
        simulate_sequence = None
    if simulate_sequence is not None:
        return simulate_sequence(tmp_path / "sim", preset="tiny-mixed", frames=60,
                                 azimuth_steps=64)
    rng = np.random.default_rng(0)
    from conftest import write_kitti_sequence
    from test_protocols import line_poses, random_scan

    xs = np.cumsum(rng.normal(0.5, 2.0, 60))
    return write_kitti_sequence(tmp_path / "walk", [random_scan(rng) for _ in range(60)],
                                line_poses(xs))


@pytest.mark.parametrize("extra", [[], ["--distance", "planar", "--pose-frame", "lidar"]])
def test_protocol2_counts_equal_liris_gt(simulated, tmp_path, capsys, extra):
    seq_dir = simulated
    code, out, err = run_cli(["gt", seq_dir, "--radius", "4", "--json", *extra], capsys)
    assert code == 0, err
    gt = json.loads(out)
    code, out, err = run_cli(["eval", seq_dir, "--protocol", "2", "-d", "toy", "--out",
                          tmp_path / "r", "--cache-dir", tmp_path / "c", "-q", "--json",
                          *extra], capsys)
    assert code == 0, err
    (row,) = json.loads(out)["results"]
    assert gt["positive_ordered_pairs"] > 0
    assert row["n_positives"] == gt["positive_ordered_pairs"]
    assert row["n_negatives"] == gt["negative_ordered_pairs"]
    assert row["n_pairs"] == gt["frames"] * (gt["frames"] - 1)


def test_failed_run_leaves_no_folder_and_keeps_the_old_one(seq_dir, tmp_path, capsys,
                                                           monkeypatch):
    from lidar_iris_eval.errors import LirisError
    from lidar_iris_eval.runs import writer as evaluate_module

    def boom(*args, **kwargs):
        raise LirisError("disk", "full")

    assert run_cli(eval_args(seq_dir, tmp_path), capsys)[0] == 0
    before = (tmp_path / "run" / "metrics.json").read_text()
    monkeypatch.setattr(evaluate_module, "write_protocol2", boom)
    code, _, err = run_cli(eval_args(seq_dir, tmp_path, "--overwrite"), capsys)
    assert_one_line_error(code, err, "disk: full")
    assert (tmp_path / "run" / "metrics.json").read_text() == before
    code, _, err = run_cli([*eval_args(seq_dir, tmp_path)[:-3], "--out", tmp_path / "new", "-q"],
                       capsys)
    assert_one_line_error(code, err, "disk: full")
    assert not (tmp_path / "new").exists()
    assert not list(tmp_path.glob(".run.*")) and not list(tmp_path.glob(".new.*"))


def test_library_evaluate_returns_what_the_cli_writes(seq_dir, tmp_path, capsys):
    from lidar_iris_eval.evaluation.evaluate import Settings, evaluate
    from lidar_iris_eval.runs.writer import write_run

    assert run_cli(eval_args(seq_dir, tmp_path), capsys)[0] == 0
    written = json.loads((tmp_path / "run" / "metrics.json").read_text())["results"]
    run = evaluate(open_sequence(seq_dir), ["toy", "toy-asym"], protocols=(2, 1),
                   settings=Settings(exclude=5), cache=tmp_path / "cache")
    assert run.protocols == (1, 2) and run.settings.exclude_name == "custom"
    timing = ("extract_ms_per_scan", "match_ms_per_query", "match_us_per_pair")
    assert len(run.rows) == len(written) == 4
    for mine, theirs in zip(run.rows, written, strict=True):
        for key, value in theirs.items():
            if key in timing:
                continue
            got = mine[key]
            if isinstance(value, float) or value is None:
                assert (got is None or not np.isfinite(got)) if value is None else \
                    got == pytest.approx(value, rel=1e-12), key
            else:
                assert got == value, key
    out = write_run(run, tmp_path / "lib-run")
    assert (out / "protocol1" / "toy" / "matches.csv").is_file()
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["convention"]["exclude"] == 5 and config["convention"]["preset"] == "custom"
