"""Issue 23: --seeds reruns the stochastic stages and reports mean and range."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from test_gosmatch_pipeline import _object_world

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.seeds import parse_seeds, spread

#: few RANSAC iterations, so that the seed matters on this small world
NOISY = ["--param", "gosmatch.ransac_iterations=3"]


@pytest.fixture(scope="module")
def objects(tmp_path_factory):
    seq, _ = _object_world(tmp_path_factory.mktemp("seeds") / "objects")
    return seq


def _eval(seq, out, cache, capsys, *extra):
    code, text, err = run_cli(["eval", seq, "-d", "gosmatch", "--protocol", "1", "--exclude",
                               "10", *NOISY, "--cache-dir", cache, "--out", out, "-q",
                               "--json", *extra], capsys)
    assert code == 0, err
    return json.loads(text)["results"][0]


def test_gosmatch_spread_contains_each_single_seed_run(objects, tmp_path, capsys):
    cache = tmp_path / "c"
    row = _eval(objects, tmp_path / "all", cache, capsys, "--seeds", "1,2,3")
    block = row["seeds"]
    assert block["seeds"] == [1, 2, 3] and block["stochastic"] is True
    for k, seed in enumerate((1, 2, 3)):
        single = _eval(objects, tmp_path / f"s{seed}", cache, capsys,
                       "--param", f"gosmatch.seed={seed}")
        for metric in ("ap", "f1_max", "rte_m_median"):
            s = block[metric]
            assert s["values"][k] == single[metric]
            assert s["min"] <= single[metric] <= s["max"]
    # the run's own figures are the first seed's; the seed matters here
    assert row["f1_max"] == block["f1_max"]["values"][0]
    assert block["ap"]["min"] < block["ap"]["max"]
    assert block["ap"]["mean"] == pytest.approx(np.mean(block["ap"]["values"]))
    for seed in (1, 2, 3):
        assert (tmp_path / "all" / "protocol1" / "gosmatch" / f"pr_seed{seed}.csv").is_file()
    code, out, _ = run_cli(["show", tmp_path / "all"], capsys)
    assert code == 0 and "1,2,3" in out and "[" in out


def test_pr_figure_draws_the_band(objects, tmp_path, capsys):
    from lidar_iris_eval.plotting.pr import pr_figure, run_curves
    from lidar_iris_eval.runs import load_run

    _eval(objects, tmp_path / "all", tmp_path / "c", capsys, "--seeds", "1,2")
    (curve,) = run_curves(load_run(tmp_path / "all"), 1)
    assert curve.band is not None and "2 seeds" in curve.label
    grid, low, high = curve.band
    assert np.all(low <= high) and np.all((0 <= low) & (high <= 1))
    fig = pr_figure([curve])
    assert "band:gosmatch" in [c.get_gid() for c in fig.axes[0].collections]


def test_parse_and_spread():
    assert parse_seeds("3,1") == (3, 1)
    for bad in ("1,1", "a", "-1", ""):
        with pytest.raises(LirisError):
            parse_seeds(bad)
    s = spread([0.5, None, 0.7])
    assert s == {"values": [0.5, None, 0.7], "mean": pytest.approx(0.6), "min": 0.5, "max": 0.7}
    assert spread([None])["mean"] is None


def test_bad_seeds_flag_is_one_line(objects, tmp_path, capsys):
    code, _, err = run_cli(["eval", objects, "-d", "gosmatch", "--protocol", "1", "--seeds",
                            "1,x", "--out", tmp_path / "r", "-q"], capsys)
    assert_one_line_error(code, err, "--seeds", "integers")


def test_config_replays_seeds_and_loop_settings(objects, tmp_path, capsys):
    first = _eval(objects, tmp_path / "a", tmp_path / "c", capsys, "--seeds", "2,3",
                  "--rr-thresholds", "1,3")
    code, out, err = run_cli(["eval", "--config", tmp_path / "a" / "config.yaml", "--out",
                              tmp_path / "b", "-q", "--json"], capsys)
    assert code == 0, err
    again = json.loads(out)
    assert again["results"][0]["seeds"] == first["seeds"]
    assert "rte_m < 1 and rre_deg < 3" in again["conventions"]["registration_recall"]
