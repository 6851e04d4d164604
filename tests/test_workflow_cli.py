"""``liris eval`` workflow options: --format, --config replay, --external, --convention."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from conftest import assert_one_line_error, run_cli
from test_rosbag import loop_poses, make_clouds, write_kitti_layout

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.extract import extract
from lidar_iris_eval.io import open_sequence

#: keys that are measurements of time or of the moment, not results
TIMING = {"extract_ms_per_scan", "match_ms_per_query", "match_us_per_pair"}
HEADER_VOLATILE = {"created", "wall_s", "host"}


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    n = 70  # 1.3 laps: the last ~20 frames revisit the first ones
    return write_kitti_layout(tmp_path_factory.mktemp("wf") / "seq", make_clouds(n, 60),
                              loop_poses(n))


def evaluate(seq, tmp_path, capsys, name, *extra):
    args = ["eval", seq, "--protocol", "1", "--protocol", "2",
            "--cache-dir", tmp_path / "cache", "--out", tmp_path / name, "-q", *extra]
    code, out, err = run_cli(args, capsys)
    assert code == 0, err
    return tmp_path / name, out, err


def comparable(metrics: dict) -> dict:
    return {**{k: v for k, v in metrics.items() if k not in HEADER_VOLATILE | {"results"}},
            "results": [{k: v for k, v in r.items() if k not in TIMING}
                        for r in metrics["results"]]}


def test_eval_markdown_equals_show_markdown(seq, tmp_path, capsys):
    run, out, err = evaluate(seq, tmp_path, capsys, "run", "-d", "m2dp", "--format", "markdown")
    assert "conventions:" in err and "conventions:" not in out  # the table stays pasteable
    code, shown, _ = run_cli(["show", run, "--format", "markdown", "--no-conventions"], capsys)
    assert code == 0
    assert shown == out
    assert out.startswith("| protocol | descriptor |")


def test_config_replays_the_run_exactly(seq, tmp_path, capsys, monkeypatch):
    # what the console script sees (in-process, sys.argv is pytest's)
    monkeypatch.setattr("sys.argv", ["/usr/bin/liris", "eval", "--frames", "0:60"])
    run, _, _ = evaluate(seq, tmp_path, capsys, "a", "-d", "m2dp,scan-context", "--frames",
                         "0:60", "--radius", "5", "--recall-denominator", "accepted",
                         "--exclude", "10")
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["command"]["argv"][:2] == ["liris", "eval"]
    assert "--frames" in config["command"]["argv"]
    assert config["command"]["liris_version"]
    assert "git" in config["command"]  # the commit, or None outside a git checkout
    code, _, err = run_cli(["eval", "--config", run / "config.yaml", "--out", tmp_path / "b",
                            "--cache-dir", tmp_path / "cache", "-q"], capsys)
    assert code == 0, err
    a = json.loads((run / "metrics.json").read_text())
    b = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert comparable(a) == comparable(b)
    assert a["sequence"]["n_frames"] == 60
    # a command-line option wins over the recorded one
    code, _, err = run_cli(["eval", "--config", run, "--radius", "3", "--out", tmp_path / "c",
                            "--cache-dir", tmp_path / "cache", "-q"], capsys)
    assert code == 0, err
    c = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert c["conventions"]["radius"] == 3.0
    assert c["conventions"]["recall_denominator"] == "accepted"
    assert [r["descriptor"] for r in c["results"]] == [r["descriptor"] for r in a["results"]]


def test_external_m2dp_vectors_reproduce_m2dp_metrics(seq, tmp_path, capsys):
    run, _, _ = evaluate(seq, tmp_path, capsys, "m2dp", "-d", "m2dp")
    code, _, err = run_cli(["extract", seq, "-d", "m2dp", "--cache-dir", tmp_path / "cache",
                            "--export-npy", tmp_path, "-q"], capsys)
    assert code == 0, err
    db = extract(open_sequence(seq), get_descriptor("m2dp"), cache=tmp_path / "cache")
    assert np.array_equal(np.load(tmp_path / "m2dp.npy"), db.descriptors)
    ext, _, _ = evaluate(seq, tmp_path, capsys, "ext", "--external", f"mine={tmp_path}/m2dp.npy")
    a = json.loads((run / "metrics.json").read_text())["results"]
    b = json.loads((ext / "metrics.json").read_text())["results"]
    skip = TIMING | {"descriptor", "preset"}
    assert [{k: v for k, v in r.items() if k not in skip} for r in a] == \
        [{k: v for k, v in r.items() if k not in skip} for r in b]
    assert b[0]["descriptor"] == "mine" and b[0]["preset"] == "external"
    assert b[0]["extract_ms_per_scan"] is None  # computed elsewhere: unknown cost
    assert np.array_equal(np.load(run / "protocol2/m2dp/affinity.npy"),
                          np.load(ext / "protocol2/mine/affinity.npy"), equal_nan=True)
    config = yaml.safe_load((ext / "config.yaml").read_text())
    assert config["descriptors"][0]["params"]["kind"] == "vectors"


def test_external_bad_files_are_one_line_errors(seq, tmp_path, capsys):
    np.save(tmp_path / "short.npy", np.ones((69, 8)))
    code, _, err = run_cli(["eval", seq, "--protocol", "1", "--external",
                            f"x={tmp_path}/short.npy", "--out", tmp_path / "r", "-q"], capsys)
    assert_one_line_error(code, err, "short.npy", "69 rows", "70 scans")
    bad = np.ones((70, 8))
    bad[5, 2] = np.inf
    np.save(tmp_path / "nan.npy", bad)
    code, _, err = run_cli(["eval", seq, "--protocol", "1", "--external",
                            f"x={tmp_path}/nan.npy", "--out", tmp_path / "r", "-q"], capsys)
    assert_one_line_error(code, err, "nan.npy", "NaN/inf", "row 5")
    code, _, err = run_cli(["eval", seq, "--protocol", "1", "--out", tmp_path / "r", "-q"],
                           capsys)
    assert_one_line_error(code, err, "--descriptor", "--external")


def test_eval_under_peer_conventions(seq, tmp_path, capsys):
    run, out, _ = evaluate(seq, tmp_path, capsys, "sc", "-d", "m2dp", "--convention",
                           "scancontext-eval")
    metrics = json.loads((run / "metrics.json").read_text())
    c = metrics["conventions"]
    assert (c["convention"], c["radius"], c["exclude"], c["distance"]) == \
        ("scancontext-eval", 5.0, 49, "planar")
    assert "last frame" in c["query_range"]
    p1 = next(r for r in metrics["results"] if r["protocol"] == 1)
    assert p1["n_queries"] == 70 - 49 - 1
    assert "convention scancontext-eval" in out
    run, _, _ = evaluate(seq, tmp_path, capsys, "sc10", "-d", "m2dp", "--convention",
                         "scancontext-eval", "--exclude", "10")  # an explicit option wins
    c = json.loads((run / "metrics.json").read_text())["conventions"]
    assert (c["convention"], c["exclude"], c["radius"]) == ("scancontext-eval+custom", 10, 5.0)
    run, _, _ = evaluate(seq, tmp_path, capsys, "lg", "-d", "m2dp", "--convention", "logg3d",
                         "--exclude", "2.5s")
    metrics = json.loads((run / "metrics.json").read_text())
    c = metrics["conventions"]
    assert c["convention"] == "logg3d+custom" and c["exclude_seconds"] == 2.5
    assert "neither true nor false" in c["not_revisit_band"]
    p1 = next(r for r in metrics["results"] if r["protocol"] == 1)
    assert p1["n_queries"] == 70 - 25  # times.txt is 0.1 s apart: queries from t >= 2.5 s


def test_eval_without_sequence_or_protocol_is_one_line(seq, tmp_path, capsys):
    code, _, err = run_cli(["eval"], capsys)
    assert_one_line_error(code, err, "SEQUENCE", "--config")
    code, _, err = run_cli(["eval", seq, "-d", "m2dp"], capsys)
    assert_one_line_error(code, err, "--protocol")
    code, _, err = run_cli(["eval", "--config", tmp_path / "nope.yaml"], capsys)
    assert_one_line_error(code, err, "nope.yaml", "not found")
