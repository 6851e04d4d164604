"""``liris eval --convention-band`` (issue 38 item 3): one matching pass, every preset.

The per-preset values must equal separate runs with ``--convention NAME``
(computed here by the CLI, each its own matching pass), and the run's own
numbers must not move when the band is asked for.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import run_cli

METRICS = ("ap", "f1_max", "r100p", "ep", "n_queries", "n_revisits", "n_true_top1")


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    from lidar_iris_eval.simulate import simulate_sequence

    root = simulate_sequence(tmp_path_factory.mktemp("band") / "sim", preset="tiny-mixed",
                             frames=110, azimuth_steps=128)
    # one scan a second: LoGG3D-Net's 30 s window is then 30 frames and has queries
    np.savetxt(root / "times.txt", np.arange(110, dtype=float), fmt="%.6f")
    return root


def _run(seq, out, capsys, *extra):
    code, _, err = run_cli(["eval", seq, "--descriptor", "scan-context,m2dp", "--cache-dir",
                            out.parent / "cache", "--out", out, "-q", *extra], capsys)
    assert code == 0, err
    return json.loads((out / "metrics.json").read_text())


def _p1(metrics):
    return {r["descriptor"]: r for r in metrics["results"] if r["protocol"] == 1}


@pytest.mark.parametrize("protocols", [["--protocol", "1"], ["--protocol", "1", "--protocol", "2"]])
def test_band_values_equal_separate_convention_runs(seq, tmp_path, capsys, protocols):
    band = _run(seq, tmp_path / "band", capsys, *protocols, "--convention-band")
    plain = _run(seq, tmp_path / "plain", capsys, *protocols)
    rows = _p1(band)
    for name in ("scancontext-eval", "logg3d"):
        separate = _p1(_run(seq, tmp_path / name, capsys, *protocols, "--convention", name))
        for desc, row in rows.items():
            assert name in row["convention_band"]["presets"]
            got = row["convention_band"]["values"][name]
            for key in METRICS:
                want = separate[desc].get(key)
                assert got[key] == pytest.approx(want, abs=1e-12), (name, desc, key)
    for desc, row in rows.items():  # the run's own numbers do not move
        own = _p1(plain)[desc]
        for key in METRICS:
            assert row[key] == own[key]
            entry = row["convention_band"]["metrics"][key]
            assert entry["own"] == pytest.approx(own[key])
            values = [v[key] for v in row["convention_band"]["values"].values()
                      if v[key] is not None]
            assert entry["min"] == min(values) and entry["max"] == max(values)
    assert "convention_band" in band["conventions"]
    assert "convention_band" not in plain["conventions"]


def test_band_records_what_it_leaves_out(seq, tmp_path, capsys):
    row = _p1(_run(seq, tmp_path / "b", capsys, "--protocol", "1", "--convention-band"))
    skipped = row["m2dp"]["convention_band"]["skipped"]
    assert "iris-cpp" in skipped  # E = 300 > 110 frames
    assert "contour-context" in skipped  # LiDAR-frame poses; this run uses camera poses
    assert "bevplace-00" in skipped


def test_band_refuses_protocol_2_alone(seq, tmp_path, capsys):
    from conftest import assert_one_line_error

    code, _, err = run_cli(["eval", seq, "--descriptor", "m2dp", "--protocol", "2",
                            "--convention-band", "--out", tmp_path / "x", "-q"], capsys)
    assert_one_line_error(code, err, "--convention-band")


def test_multi_limit_reduction_equals_one_limit_at_a_time():
    from lidar_iris_eval.matching.blocks import _best_in_block, _best_under_limits

    rng = np.random.default_rng(3)
    d = rng.integers(0, 5, size=(40, 60)).astype(float)  # many ties
    d[rng.random(d.shape) < 0.1] = np.nan
    y = rng.normal(size=d.shape)
    limits = rng.integers(-1, 60, size=(5, 40))
    m, dist, yaw = _best_under_limits(d, y, limits)
    for k in range(5):
        m1, d1, y1 = _best_in_block(d, y, limits[k])
        assert np.array_equal(m[k], m1) and np.array_equal(dist[k], d1)
        assert np.array_equal(yaw[k], y1, equal_nan=True)


def test_show_compare_and_report_display_the_band(seq, tmp_path, capsys):
    band_dir, plain_dir = tmp_path / "band", tmp_path / "plain"
    row = _p1(_run(seq, band_dir, capsys, "--protocol", "1", "--convention-band"))["m2dp"]
    _run(seq, plain_dir, capsys, "--protocol", "1")
    ap = row["convention_band"]["metrics"]["ap"]
    code, out, err = run_cli(["show", band_dir], capsys)
    assert code == 0, err
    assert "convention band" in out
    assert f"[{ap['min']:.4f}–{ap['max']:.4f}]" in out
    code, out, err = run_cli(["show", plain_dir], capsys)
    assert code == 0 and "convention band" not in out  # old and plain runs: as before
    code, out, err = run_cli(["compare", plain_dir, band_dir], capsys)
    assert code == 0, err
    assert f"[{ap['min']:.4f}–{ap['max']:.4f}]" in out
    presets = row["convention_band"]["presets"]
    for name in presets:
        assert (band_dir / "protocol1" / "m2dp" / f"pr_convention-{name}.csv").is_file()
    from lidar_iris_eval.plotting import load_run
    from lidar_iris_eval.plotting.pr import run_curves

    curves = {c.key: c for c in run_curves(load_run(band_dir), 1)}
    assert curves["m2dp"].band is not None  # the PR figure's shaded spread
    assert all(c.band is None for c in run_curves(load_run(plain_dir), 1))
    pytest.importorskip("plotly")
    code, _, err = run_cli(["report", band_dir, "--failures", "0"], capsys)
    assert code == 0, err
    page = (band_dir / "report" / "index.html").read_text()
    assert "id='convention-band'" in page and f"{len(presets)} conventions" in page


def test_edited_band_is_one_error(seq, tmp_path, capsys):
    from conftest import assert_one_line_error

    out = tmp_path / "band"
    metrics = _run(seq, out, capsys, "--protocol", "1", "--convention-band")
    metrics["results"][0]["convention_band"]["metrics"]["ap"]["max"] = 1.5
    (out / "metrics.json").write_text(json.dumps(metrics))
    code, _, err = run_cli(["show", out], capsys)
    assert_one_line_error(code, err, "convention_band.metrics.ap.max")


def test_two_stage_band_keeps_only_presets_with_the_same_window(seq, tmp_path, capsys,
                                                                   monkeypatch):
    """Retrieval depends on each query's database: a two-stage method's band holds the
    presets whose windows equal the run's, and those equal separate runs."""
    from lidar_iris_eval.descriptors import _REGISTRY

    monkeypatch.setitem(_REGISTRY, "toy-objects", "toy_two_stage:ToyObjects")

    def run(out, *extra):
        code, _, err = run_cli(["eval", seq, "--descriptor", "toy-objects", "--protocol", "1",
                                "--cache-dir", tmp_path / "cache", "--out", out, "-q", *extra],
                               capsys)
        assert code == 0, err
        return _p1(json.loads((out / "metrics.json").read_text()))["toy-objects"]

    # E = 49 is Scan Context's evaluator's window: same databases, other ground-truth rules
    band = run(tmp_path / "band", "--exclude", "49", "--convention-band")["convention_band"]
    assert band["presets"] == ["scancontext-eval"]
    assert "two-stage" in band["skipped"]["liris"] and "two-stage" in band["skipped"]["logg3d"]
    separate = run(tmp_path / "sc", "--convention", "scancontext-eval")
    for key in METRICS:
        assert band["values"]["scancontext-eval"][key] == pytest.approx(separate[key])


def test_distributed_block_paths_give_the_same_band(seq):
    """The block-task paths (a Dask cluster's) reduce (K, N) limits as the local pass does."""
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.evaluation.band import band_plan
    from lidar_iris_eval.evaluation.ground_truth import database_limits
    from lidar_iris_eval.evaluation.protocol2 import protocols_1_and_2
    from lidar_iris_eval.evaluation.settings import Settings
    from lidar_iris_eval.executor import SerialExecutor
    from lidar_iris_eval.extract import extract_many
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.matching.blocks import best_matches

    class BlockTasks(SerialExecutor):
        """Serial, but answers as a cluster does: block tasks return reductions only."""

        def run_blocks(self, fn, tasks, shared=(), warm_up=None, threaded=False):
            return self.imap(fn, tasks, shared)

        def returns_blocks(self):
            return False

    sequence = open_sequence(seq)
    desc = get_descriptor("m2dp")
    db = extract_many(sequence, [desc])[0]
    settings = Settings()
    plan = band_plan(sequence, settings, sequence.resolve_pose_frame("camera"))
    own = database_limits(len(sequence), settings)
    stacked = np.vstack([own[None, :], plan.limits])
    local = best_matches(desc, db.descriptors, stacked, 4096)
    tasks = best_matches(desc, db.descriptors, stacked, 4096, executor=BlockTasks())
    positions = sequence.positions("camera")
    p1, _ = protocols_1_and_2(desc, db.descriptors, positions, settings,
                              band_limits=plan.limits, executor=BlockTasks())
    for k, (a, b) in enumerate(zip(local, tasks, strict=True)):
        assert np.array_equal(a.query, b.query) and np.array_equal(a.match, b.match)
        assert np.array_equal(a.distance, b.distance)
        one = best_matches(desc, db.descriptors, stacked[k], 4096)  # one limit at a time
        assert np.array_equal(one.match, a.match) and np.array_equal(one.query, a.query)
        streamed = p1.matches if k == 0 else p1.band_matches[k - 1]
        assert np.array_equal(streamed.match, a.match)


@pytest.mark.parametrize("name, frames, has_bevplace", [("00", 4541, True), ("05", 4541, False),
                                                         ("00", 3100, False)])
def test_bevplace_split_applies_only_to_its_kitti_sequence(name, frames, has_bevplace):
    from types import SimpleNamespace

    from lidar_iris_eval.evaluation.band import band_plan
    from lidar_iris_eval.evaluation.settings import Settings

    seq = SimpleNamespace(name=name, times=np.arange(frames) * 0.1,
                          camera_poses=np.zeros((frames, 4, 4)))
    plan = band_plan(_Sized(seq, frames), Settings(), "camera")
    names = [p.name for p in plan.presets]
    assert ("bevplace-00" in names) == has_bevplace
    assert "bevplace-02" not in names and "contour-context" not in names  # lidar frame
    for p, lim in zip(plan.presets, plan.limits, strict=True):
        assert p.pose_frame == "camera" and np.any(lim >= 0)


class _Sized:
    def __init__(self, ns, n):
        self.__dict__.update(vars(ns))
        self._n = n

    def __len__(self):
        return self._n
