"""Descriptor and reader options shared by ``liris extract`` and ``liris eval``."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from conftest import run_cli, write_kitti_sequence


@pytest.fixture
def seq(tmp_path):
    rng = np.random.default_rng(0)
    scans = [np.c_[rng.uniform(-30, 30, (500, 2)), rng.uniform(-2, 3, (500, 2))]
             for _ in range(6)]
    poses = np.tile(np.eye(4), (6, 1, 1))
    poses[:, 2, 3] = np.arange(6) * 1.0
    return write_kitti_sequence(tmp_path / "seq", scans, poses)


def _config(tmp_path, seq, capsys, *extra):
    out = tmp_path / "run"
    code, _, err = run_cli(["eval", str(seq), "--protocol", "2", "--descriptor", "lidar-iris",
                        "--cache-dir", str(tmp_path / "cache"), "--out", str(out), "-q",
                        *extra], capsys)
    assert code == 0, err
    return yaml.safe_load((out / "config.yaml").read_text())


def test_sensor_vlp16_uses_the_papers_vlp16_height_range(tmp_path, seq, capsys):
    params = _config(tmp_path, seq, capsys, "--sensor", "vlp16")["descriptors"][0]["params"]
    assert (params["z_low"], params["z_high"]) == (-2.0, 22.0)


def test_default_sensor_is_the_hdl64_range(tmp_path, seq, capsys):
    params = _config(tmp_path, seq, capsys)["descriptors"][0]["params"]
    assert (params["z_low"], params["z_high"]) == (-3.0, 5.0)


def test_param_override_reaches_the_descriptor(tmp_path, seq, capsys):
    config = _config(tmp_path, seq, capsys, "--param", "lidar-iris.shift_window=3")
    assert config["descriptors"][0]["params"]["shift_window"] == 3


@pytest.mark.parametrize(("param", "fragment"), [
    ("lidar-iris.no_such_key=1", "unknown config key(s) no_such_key"),
    ("esf.seed=1", "'esf' is not among --descriptor"),
    ("seed=1", "expected DESCRIPTOR.KEY=VALUE"),
])
def test_bad_param_is_a_one_line_error(seq, capsys, tmp_path, param, fragment):
    code, _, err = run_cli(["extract", str(seq), "--descriptor", "lidar-iris", "--cache-dir",
                        str(tmp_path / "c"), "--param", param], capsys)
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and fragment in lines[0]


def test_unknown_descriptor_is_a_one_line_error(seq, capsys):
    code, _, err = run_cli(["extract", str(seq), "--descriptor", "iris-2"], capsys)
    assert code == 2 and err.count("\n") == 1
    assert "--descriptor iris-2: unknown descriptor" in err


def test_poses_option_overrides_the_sequence_poses(tmp_path, seq, capsys):
    # the same trajectory stretched 10x: no pair is within 4 m any more
    far = np.loadtxt(seq / "poses.txt")
    far[:, 11] *= 10
    np.savetxt(tmp_path / "far.txt", far)
    code, out, err = run_cli(["eval", str(seq), "--protocol", "2", "--descriptor", "m2dp",
                          "--poses", str(tmp_path / "far.txt"), "--cache-dir",
                          str(tmp_path / "cache"), "--out", str(tmp_path / "run"), "-q",
                          "--json"], capsys)
    assert code == 0, err
    assert json.loads(out)["results"][0]["n_positives"] == 0
