"""Issue 26: the fault cases of the 440-case run, one test each (all failed on e1cbecf).

Each bad input must end in one ``liris: error: <file or flag>: <problem>`` line
(exit 2, no traceback) or in the right result; the shared mechanisms are
tested here, not one branch per case: the plausibility rules of io/, the cache
key and chunk check of cache.py, the schemas of config.py and runs/schema.py,
the atomic writer, and the warnings stored with the results.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import assert_one_line_error, run_cli, write_kitti_sequence
from synthetic_loop import loop_sequence

from lidar_iris_eval.errors import LirisError, LirisWarning

FRAMES = 40


# ---- fixtures --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> Path:
    """A 40-frame loop sequence and an m2dp run (protocols 1 and 2) of it."""
    from lidar_iris_eval.cli import main

    root = tmp_path_factory.mktemp("faults")
    seq = loop_sequence(root / "seq", frames=FRAMES)
    for args in (["eval", seq, "-d", "m2dp", "--protocol", "1", "--protocol", "2",
                  "--exclude", "5", "--cache-dir", root / "cache", "--out", root / "run", "-q"],
                 ["eval", seq, "-d", "scan-context", "--protocol", "1", "--exclude", "5",
                  "--cache-dir", root / "cache", "--out", root / "run-sc", "-q"]):
        try:
            main([str(a) for a in args])
        except SystemExit as exit_:
            assert exit_.code == 0
    return root


@pytest.fixture
def seq(base, tmp_path) -> Path:
    return Path(shutil.copytree(base / "seq", tmp_path / "seq"))


@pytest.fixture
def run_dir(base, tmp_path) -> Path:
    return Path(shutil.copytree(base / "run", tmp_path / "run"))


def edit_first_row(run: Path, key: str, value) -> None:
    path = run / "metrics.json"
    data = json.loads(path.read_text())
    data["results"][0][key] = value
    path.write_text(json.dumps(data))


def scan_file(seq: Path, i: int) -> Path:
    return seq / "velodyne" / f"{i:06d}.bin"


def original(seq: Path, i: int) -> np.ndarray:
    return np.fromfile(scan_file(seq, i), dtype=np.float32).reshape(-1, 4)


def enospc(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def no_temps(folder: Path) -> list[Path]:
    return [p for p in Path(folder).rglob("*") if ".tmp" in p.name]


# ---- scans: rule finite-plausible-coordinates -------------------------------------------


def test_float64_bin_is_rejected(seq):
    from lidar_iris_eval.io.scans import read_kitti_bin

    path = scan_file(seq, 3)
    original(seq, 3).astype(np.float64).tofile(path)  # 32 bytes a point: a multiple of 16
    with pytest.raises(LirisError, match=r"000003\.bin: implausible coordinates.*float64"):
        read_kitti_bin(path)


def test_float64_bin_of_arbitrary_values_is_rejected(seq):
    from lidar_iris_eval.io.scans import read_kitti_bin

    path = scan_file(seq, 3)
    (original(seq, 3).astype(np.float64) * 1.37 + 1e-3).tofile(path)
    with pytest.raises(LirisError, match="finite-plausible-coordinates"):
        read_kitti_bin(path)


def test_random_bytes_bin_is_rejected(tmp_path):
    from lidar_iris_eval.io.scans import read_kitti_bin

    path = tmp_path / "000000.bin"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 16 * 4000, np.uint8).tobytes())
    with pytest.warns(LirisWarning), pytest.raises(LirisError, match="implausible"):
        read_kitti_bin(path)


def test_scan_in_micrometres_scaled_up_is_rejected(seq):
    from lidar_iris_eval.io.scans import read_kitti_bin

    (original(seq, 2) * 1e7).tofile(scan_file(seq, 2))
    with pytest.raises(LirisError, match=r"000002\.bin: implausible"):
        read_kitti_bin(scan_file(seq, 2))


def test_random_pcd_body_is_rejected(tmp_path):
    from lidar_iris_eval.io.pcd import read_pcd

    n = 3000
    head = ("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
            f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n")
    body = np.random.default_rng(1).integers(0, 256, 12 * n, np.uint8).tobytes()
    path = tmp_path / "000006.pcd"
    path.write_bytes(head.encode() + body)
    with pytest.warns(LirisWarning), pytest.raises(LirisError, match=r"000006\.pcd: implausible"):
        read_pcd(path)


def test_plausibility_keeps_real_scans_and_exact_zeros(seq):
    """The rule must not reject a real scan, nor the exact zeros of no-return points."""
    from lidar_iris_eval.io.scans import read_kitti_bin

    data = original(seq, 1)
    data[:50, :3] = 0.0  # Ouster-style no-return points
    data[50, 0] = 2e6  # one stray far point: under 1 % of the points
    data.tofile(scan_file(seq, 1))
    scan = read_kitti_bin(scan_file(seq, 1))
    assert len(scan.points) == len(data)


# ---- labels: rules label-count and label-classes -------------------------------------------


def labelled(seq: Path) -> Path:
    (seq / "labels").mkdir()
    for i in range(FRAMES):
        n = len(original(seq, i))
        (np.full(n, 50, "<u4") | (np.arange(n, dtype="<u4") << 16)).tofile(
            seq / "labels" / f"{i:06d}.label")
    return seq


def test_random_bytes_label_file_is_rejected(seq):
    from lidar_iris_eval.io import open_sequence

    labelled(seq)
    path = seq / "labels" / "000012.label"
    path.write_bytes(np.random.default_rng(5).integers(0, 256, path.stat().st_size,
                                                       np.uint8).tobytes())
    with pytest.raises(LirisError, match=r"000012\.label: .*not a SemanticKITTI class"):
        open_sequence(seq).scan(12)


def test_known_class_ids_pass_with_instances(seq):
    from lidar_iris_eval.io.scans import check_label_classes

    check_label_classes(np.array([10, 252 | (7 << 16), 0, 99], np.uint32), "x")
    with pytest.raises(LirisError, match="first: 12 at point 1; rule label-classes"):
        check_label_classes(np.array([10, 12], np.uint32), "x.label")


# ---- poses and calibration: rule orthonormal-rotation --------------------------------------


def set_pose_line(path: Path, index: int, values) -> None:
    lines = path.read_text().splitlines()
    lines[index] = " ".join(f"{v:.6e}" for v in values)
    path.write_text("\n".join(lines) + "\n")


def test_zero_rotation_pose_names_file_and_line(seq):
    from lidar_iris_eval.io.poses import read_kitti_poses

    set_pose_line(seq / "poses.txt", 10, [0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3])
    with pytest.raises(LirisError, match=r"poses\.txt:11: KITTI pose: rotation is not "
                                         r"orthonormal.*rule orthonormal-rotation"):
        read_kitti_poses(seq / "poses.txt")


def test_scaled_and_mirrored_rotations_are_rejected(seq):
    from lidar_iris_eval.io.poses import read_kitti_poses

    set_pose_line(seq / "poses.txt", 4, [2, 0, 0, 1, 0, 2, 0, 2, 0, 0, 2, 3])
    with pytest.raises(LirisError, match=r"poses\.txt:5"):
        read_kitti_poses(seq / "poses.txt")
    set_pose_line(seq / "poses.txt", 4, [1, 0, 0, 1, 0, 1, 0, 2, 0, 0, -1, 3])
    with pytest.raises(LirisError, match="reflection"):
        read_kitti_poses(seq / "poses.txt")


def test_zero_rotation_pose_fails_eval_in_one_line(seq, tmp_path, capsys):
    set_pose_line(seq / "poses.txt", 10, [0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3])
    code, _, err = run_cli(["gt", seq, "--pose-frame", "lidar"], capsys)
    assert_one_line_error(code, err, "poses.txt:11", "orthonormal")


def test_gt_lidar_frame_with_zero_tr_is_one_line(seq, capsys):
    (seq / "calib.txt").write_text("Tr: " + " ".join(["0"] * 12) + "\n")
    code, _, err = run_cli(["gt", seq, "--pose-frame", "lidar"], capsys)
    assert_one_line_error(code, err, "calib.txt:1", "Tr")


# ---- cache: key covers declared inputs; chunks hold the rows their name says ------------------


def test_cache_key_covers_the_labels_of_a_labelled_method(seq):
    from test_scan_inputs import ClassCentroids, ClassParams

    from lidar_iris_eval.extract import cache_key
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.simulate.writer import atomic_write

    labelled(seq)
    desc = ClassCentroids(ClassParams(classes=(50, 51, 52)))
    before = cache_key(open_sequence(seq), desc).digest()
    path = seq / "labels" / "000012.label"
    atomic_write(path, b"")  # the issue's `: > L/labels/000012.label`
    assert cache_key(open_sequence(seq), desc).digest() != before


def test_cache_key_of_a_scan_only_method_ignores_labels(seq):
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.extract import cache_key
    from lidar_iris_eval.io import open_sequence

    labelled(seq)
    desc = get_descriptor("m2dp")
    key = cache_key(open_sequence(seq), desc)
    assert key.inputs == ""
    shutil.rmtree(seq / "labels")
    assert cache_key(open_sequence(seq), desc).digest() == key.digest()


def test_stale_labels_are_not_served_from_the_cache(seq, tmp_path):
    """The issue's steps: cache, then empty a label file: the rerun must see it."""
    from test_scan_inputs import ClassCentroids, ClassParams

    from lidar_iris_eval.extract import extract
    from lidar_iris_eval.io import open_sequence

    labelled(seq)
    desc = ClassCentroids(ClassParams(classes=(50, 51, 52)))
    extract(open_sequence(seq), desc, cache=tmp_path / "cache")
    (seq / "labels" / "000012.label").write_bytes(b"")
    with pytest.raises(LirisError, match=r"000012\.label: 0 labels but"):
        extract(open_sequence(seq), desc, cache=tmp_path / "cache")


def test_a_chunk_copied_over_another_is_rejected(tmp_path):
    from lidar_iris_eval.cache import CacheKey, DescriptorCache

    cache = DescriptorCache(tmp_path)
    key = CacheKey.build("s", "f", "esf", {}, "v", 40)
    rows = {"descriptors": np.arange(20.0)[:, None], "extract_s": np.zeros(20),
            "read_s": np.zeros(20)}
    cache.store_chunk(key, 0, 20, rows)
    cache.store_chunk(key, 20, 40, {k: v + 1 for k, v in rows.items()})
    folder = cache.partial_dir(key)
    shutil.copy(folder / "chunk-000000000-000000020.npz", folder / "chunk-000000020-000000040.npz")
    with pytest.warns(LirisWarning, match="holds rows 0-20, not the 20-40"):
        chunks = cache.load_chunks(key)
    assert list(chunks) == [(0, 20)]


# ---- descriptors: the scan that fails, parameters, external files ----------------------------


def test_one_point_scan_error_names_the_scan(seq, capsys):
    original(seq, 3)[:1].tofile(scan_file(seq, 3))
    code, _, err = run_cli(["extract", seq, "-d", "m2dp", "--frames", "0:10", "-q",
                            "--cache-dir", seq / "cache"], capsys)
    assert_one_line_error(code, err, "000003.bin", "at least 3")


def test_empty_param_value_is_one_line(seq, capsys):
    code, _, err = run_cli(["extract", seq, "-d", "lidar-iris", "--param",
                            "lidar-iris.rings=", "-q"], capsys)
    assert_one_line_error(code, err, "rings", "no value")


def test_huge_integer_param_is_refused_before_any_work(seq, capsys):
    code, _, err = run_cli(["extract", seq, "-d", "lidar-iris", "--param",
                            "lidar-iris.rings=100000000000", "-q"], capsys)
    assert_one_line_error(code, err, "rings", "integer-parameter-range")


def test_negative_seed_param_is_refused():
    from lidar_iris_eval.descriptors import get_descriptor

    with pytest.raises(LirisError, match="seed"):
        get_descriptor("esf", seed=-1)


def test_external_npz_is_one_line(seq, capsys):
    np.savez(seq / "f.npz", a=np.zeros((FRAMES, 4)))
    code, _, err = run_cli(["eval", seq, "--protocol", "1", "--external", f"net={seq}/f.npz",
                            "-q", "--out", seq / "r"], capsys)
    assert_one_line_error(code, err, "f.npz", ".npy")


@pytest.mark.parametrize("array", [
    np.ones((FRAMES, 8)),  # every row constant
    np.tile(np.arange(8.0), (FRAMES, 1)),  # every scan the same descriptor
    np.random.default_rng(0).random((FRAMES, 8)) * 1e200,  # squared distances overflow
], ids=["constant", "identical", "overflow"])
def test_degenerate_external_descriptors_are_warned_about(seq, array):
    from lidar_iris_eval.descriptors.external import load_external
    from lidar_iris_eval.extract import external_database

    np.save(seq / "f.npy", array)
    desc = load_external("net", seq / "f.npy", FRAMES)
    with pytest.warns(LirisWarning, match="cannot mean much"):
        db = external_database(desc, "seq")
    assert db.warnings and "net" in db.warnings[0]


# ---- config files: one strict schema ---------------------------------------------------------


@pytest.mark.parametrize("edit, fragment", [
    ({"exclude": 30}, "exclude: expected a mapping"),
    ({"descriptors": "lidar-iris"}, "descriptors: expected a list"),
    ({"radious": 5}, "unknown key(s) radious"),
    ({"engine": {"scheduler": "foo"}}, "engine.scheduler: 'foo' is not valid"),
])
def test_eval_config_is_strict(base, tmp_path, capsys, edit, fragment):
    config = yaml.safe_load((base / "run" / "config.yaml").read_text())
    config.update(edit)
    path = tmp_path / "c.yaml"
    path.write_text(yaml.safe_dump(config))
    code, _, err = run_cli(["eval", "--config", path, "-q", "--out", tmp_path / "r"], capsys)
    assert_one_line_error(code, err, "c.yaml", fragment)


def test_a_recorded_config_still_replays(base, tmp_path):
    from lidar_iris_eval.runs.replay import read_config

    assert read_config(base / "run")["descriptors"][0]["name"] == "m2dp"


# ---- metrics.json: one schema check when a run is read ------------------------------------------


@pytest.mark.parametrize("command", ["compare", "plot", "show", "report"])
@pytest.mark.parametrize("key, value", [("ap", "high"), ("protocol", "one")])
def test_malformed_metrics_is_one_line_for_every_reader(base, run_dir, tmp_path, capsys,
                                                         command, key, value):
    if command == "report":
        pytest.importorskip("plotly")
    edit_first_row(run_dir, key, value)
    argv = {"compare": ["compare", base / "run", run_dir], "plot": ["plot", run_dir],
            "show": ["show", run_dir], "report": ["report", run_dir]}[command]
    code, _, err = run_cli(argv, capsys)
    assert_one_line_error(code, err, "metrics.json", f"results[0].{key}")


# ---- compare -------------------------------------------------------------------------------------


def test_compare_counts_only_comparable_values(base, capsys):
    """m2dp (P1, P2) against scan-context (P1): no value is comparable, so 0 differ."""
    code, out, err = run_cli(["compare", base / "run", base / "run-sc"], capsys)
    assert code == 0, err
    line = next(x for x in out.splitlines() if "metric value(s) differ" in x)
    assert line.startswith("0 metric value(s) differ") and "of 0 comparable" in line


def test_compare_difference_counts_by_hand():
    from lidar_iris_eval.runs.compare import difference_counts

    rows = [{"a": 1.0, "b": 1.0}, {"a": 1.0, "b": 2.0}, {"a": None, "b": 3.0},
            {"a": None, "b": None}]
    assert difference_counts(rows, ["a", "b"]) == (1, 2, 1)


def test_compare_plot_with_unknown_suffix_is_one_line(base, tmp_path, capsys):
    code, _, err = run_cli(["compare", base / "run", base / "run", "--plot",
                            tmp_path / "x.jpg2"], capsys)
    assert_one_line_error(code, err, "--plot", "x.jpg2", "image format")
    assert not list(tmp_path.iterdir())


def test_compare_plot_legend_sits_outside_the_curves(base, tmp_path, monkeypatch):
    import matplotlib.figure

    from lidar_iris_eval.runs import load_run
    from lidar_iris_eval.runs.compare import plot_pr_overlay

    seen = []
    real = matplotlib.figure.Figure.savefig

    def spy(fig, *args, **kwargs):
        seen.append(fig)
        return real(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", spy)
    plot_pr_overlay([load_run(base / "run"), load_run(base / "run-sc")], tmp_path / "x.png")
    fig = seen[0]
    assert all(ax.get_legend() is None for ax in fig.axes)
    assert len(fig.legends) == 1
    fig.canvas.draw()
    legend = fig.legends[0].get_window_extent()
    for ax in fig.axes:
        assert not legend.overlaps(ax.get_window_extent())


# ---- simulate ------------------------------------------------------------------------------------


def test_simulate_huge_azimuth_steps_is_one_line_and_leaves_nothing(tmp_path, capsys):
    code, _, err = run_cli(["simulate", tmp_path / "X", "--azimuth-steps", "100000000", "-q"],
                           capsys)
    assert_one_line_error(code, err, "--azimuth-steps")
    assert not (tmp_path / "X").exists()


def test_simulate_negative_seed_is_one_line(tmp_path, capsys):
    code, _, err = run_cli(["simulate", tmp_path / "X", "--seed", "-1", "-q"], capsys)
    assert_one_line_error(code, err, "--seed")


def test_interrupted_simulate_leaves_no_partial_sequence(tmp_path, monkeypatch):
    from lidar_iris_eval.simulate import pipeline

    real = pipeline.simulate_scan
    calls = []

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(pipeline, "simulate_scan", interrupted)
    with pytest.raises(KeyboardInterrupt):
        pipeline.simulate_sequence(tmp_path / "X", frames=6, azimuth_steps=64)
    assert not (tmp_path / "X").exists()
    assert not list(tmp_path.iterdir())  # nor its temporary folder


# ---- full disk: one atomic writer names the path and leaves no temporary file ------------


def test_atomic_write_on_full_disk_names_the_target(tmp_path):
    from lidar_iris_eval.atomic import atomic_write

    with pytest.raises(LirisError, match=r"out\.bin: cannot write the thing: no space left"):
        atomic_write(tmp_path / "out.bin", enospc, what="thing")
    assert not list(tmp_path.iterdir())


def test_plot_on_full_disk_names_the_figure(run_dir, tmp_path, monkeypatch, capsys):
    import matplotlib.figure

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", enospc)
    code, _, err = run_cli(["plot", run_dir, "--out", tmp_path / "figs"], capsys)
    assert_one_line_error(code, err, "figs/", "no space left")
    assert not no_temps(tmp_path / "figs")


def test_compare_plot_on_full_disk_names_the_file(base, tmp_path, monkeypatch, capsys):
    import matplotlib.figure

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", enospc)
    code, _, err = run_cli(["compare", base / "run", base / "run", "--plot",
                            tmp_path / "x.png"], capsys)
    assert_one_line_error(code, err, "x.png", "no space left")
    assert not list(tmp_path.iterdir())


def test_simulate_on_full_disk_names_the_file_and_leaves_nothing(tmp_path, monkeypatch,
                                                                 capsys):
    from lidar_iris_eval.simulate import writer

    real = writer.write_scan

    def full(out_dir, index, *args, **kwargs):
        if index == 2:
            from lidar_iris_eval.atomic import atomic_write

            atomic_write(Path(out_dir) / "velodyne" / "000002.bin", enospc)
        return real(out_dir, index, *args, **kwargs)

    from lidar_iris_eval.simulate import pipeline

    monkeypatch.setattr(pipeline, "write_scan", full)
    code, _, err = run_cli(["simulate", tmp_path / "X", "--frames", "5", "--azimuth-steps",
                            "64", "-q"], capsys)
    assert_one_line_error(code, err, "000002.bin", "no space left")
    assert not list(tmp_path.iterdir())


def test_export_loops_on_full_disk_names_the_file(seq, tmp_path, monkeypatch, capsys):
    from lidar_iris_eval import atomic

    real = atomic.os.replace

    def full(src, dst):
        if str(dst).endswith("loops.txt"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", full)
    code, _, err = run_cli(["eval", seq, "-d", "m2dp", "--protocol", "1", "--exclude", "5",
                            "--cache-dir", tmp_path / "c", "--out", tmp_path / "r", "-q",
                            "--export-loops", tmp_path / "loops.txt"], capsys)
    errors = "".join(line + "\n" for line in err.splitlines()
                     if not line.startswith("liris: warning:"))  # m2dp loops have no pose
    assert_one_line_error(code, errors, "loops.txt", "no space left")
    assert not no_temps(tmp_path)


def test_report_on_full_disk_names_the_report(run_dir, tmp_path, monkeypatch, capsys):
    pytest.importorskip("plotly")
    real = Path.write_text

    def full(self, *args, **kwargs):
        if self.name == "index.html":
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full)
    code, _, err = run_cli(["report", run_dir, "--out", tmp_path / "rep"], capsys)
    assert_one_line_error(code, err, "rep/index.html", "no space left")
    assert not list(tmp_path.glob(".rep*"))


def test_export_npy_on_full_disk_names_the_file(seq, tmp_path, monkeypatch, capsys):
    real = np.save

    def full(file, *args, **kwargs):
        if not isinstance(file, (str, os.PathLike)):  # the export's open handle
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(file, *args, **kwargs)

    monkeypatch.setattr(np, "save", full)
    code, _, err = run_cli(["extract", seq, "-d", "m2dp", "--cache-dir", tmp_path / "c",
                            "-q", "--export-npy", tmp_path / "E"], capsys)
    assert_one_line_error(code, err, "E/m2dp.npy", "no space left")
    assert not list((tmp_path / "E").iterdir())


def test_export_npy_files_follow_the_umask(seq, tmp_path, capsys):
    old = os.umask(0o022)
    try:
        code, _, err = run_cli(["extract", seq, "-d", "m2dp", "--cache-dir", tmp_path / "c",
                                "-q", "--export-npy", tmp_path / "E"], capsys)
    finally:
        os.umask(old)
    assert code == 0, err
    modes = {p.stat().st_mode & 0o777 for p in (tmp_path / "E").glob("*.npy")}
    assert modes == {0o644}


# ---- flags ---------------------------------------------------------------------------------------


def test_workers_beyond_the_cpus_are_clamped_with_a_warning(seq, tmp_path, capsys):
    from lidar_iris_eval.cli import usable_cpus

    code, _, err = run_cli(["extract", seq, "-d", "m2dp", "--workers", "1000", "-q",
                            "--cache-dir", tmp_path / "c"], capsys)
    assert code == 0, err
    assert f"--workers 1000: more than the {usable_cpus()} usable CPU(s)" in err


def test_bench_unknown_world_names_world(capsys):
    code, _, err = run_cli(["bench", "--world", "nope"], capsys)
    assert_one_line_error(code, err, "--world")


def test_frames_as_a_bare_count_in_eval_explains_the_range(seq, capsys):
    code, _, err = run_cli(["gt", seq, "--frames", "100"], capsys)
    assert_one_line_error(code, err, "--frames 100", "0:100 keeps the first 100 frames")


# ---- results: plot, report, protocol 2 timing, stored warnings ---------------------------


def test_plot_of_a_run_without_lidar_iris_draws_no_iris_figures(run_dir, tmp_path, monkeypatch):
    from lidar_iris_eval.plotting import figures

    def forbidden(*args, **kwargs):
        raise AssertionError("LiDAR Iris figures drawn for a run that did not score it")

    monkeypatch.setattr(figures, "build_iris", forbidden)
    written = figures.plot_run(run_dir, tmp_path / "figs", "png")
    assert not [p for p in written if "iris" in p.name]


def test_html_and_png_trajectories_count_alike(run_dir):
    """Both figures: TP + wrong + missed = revisits; a wrong match is not a false alarm."""
    go = pytest.importorskip("plotly.graph_objects")
    import pandas as pd

    from lidar_iris_eval.plotting.trajectory import outcome_counts, outcomes
    from lidar_iris_eval.report_html.page import trajectory_figure
    from lidar_iris_eval.runs import load_run

    # make three revisit queries' matches wrong but accepted: wrong matches on revisits
    path = run_dir / "protocol1" / "m2dp" / "matches.csv"
    matches = pd.read_csv(path)
    revisit = matches[matches["is_revisit"].astype(bool)].index
    matches.loc[revisit[:3], "is_true"] = 0 if matches["is_true"].dtype.kind in "iu" else False
    matches.loc[revisit[:3], "distance"] = 0.0
    matches.to_csv(path, index=False)
    run = load_run(run_dir)
    result = outcomes(run.matches("m2dp"), run.row(1, "m2dp")["f1_threshold"])
    png = outcome_counts(result)
    assert png["wrong"] >= 3
    assert png["tp"] + png["wrong"] + png["missed"] == result.n_revisits
    fig = trajectory_figure(run, go)
    html = {t.name.split(": ", 1)[1].rsplit(" (", 1)[0]: int(t.name.rsplit("(", 1)[1][:-1])
            for t in fig.data if t.name.startswith("m2dp: ")}
    assert html == {"true positive": png["tp"], "wrong match (revisit)": png["wrong"],
                    "missed revisit": png["missed"],
                    "false alarm (no revisit)": png["false_alarm"]}


def test_protocol2_on_one_frame_stores_no_time_per_pair(seq, tmp_path, capsys):
    code, _, err = run_cli(["eval", seq, "-d", "m2dp", "--protocol", "2", "--frames", "0:1",
                            "--cache-dir", tmp_path / "c", "--out", tmp_path / "r", "-q"], capsys)
    assert code == 0, err
    row = json.loads((tmp_path / "r" / "metrics.json").read_text())["results"][0]
    assert row["n_pairs"] == 0 and row["match_us_per_pair"] is None


@pytest.fixture
def warned_run(seq, tmp_path, capsys) -> Path:
    np.save(seq / "f.npy", np.ones((FRAMES, 8)))
    code, _, err = run_cli(["eval", seq, "--protocol", "1", "--exclude", "5", "--external",
                            f"net={seq}/f.npy", "-q", "--out", tmp_path / "w"], capsys)
    assert code == 0 and "cannot mean much" in err, err
    return tmp_path / "w"


def test_degenerate_warning_is_stored_with_the_result(warned_run):
    row = json.loads((warned_run / "metrics.json").read_text())["results"][0]
    assert len(row["warnings"]) == 1 and "constant net descriptor" in row["warnings"][0]


@pytest.mark.parametrize("command", ["show", "compare"])
def test_show_and_compare_print_the_stored_warning(warned_run, base, capsys, command):
    argv = ["show", warned_run] if command == "show" else ["compare", base / "run", warned_run]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    assert "warning" in out and "constant net descriptor" in out


def test_report_shows_the_stored_warning(warned_run):
    pytest.importorskip("plotly")
    from lidar_iris_eval.report_html.page import build_report

    page = build_report(warned_run).read_text()
    assert "Warnings that qualify these results" in page and "constant net descriptor" in page


# ---- a new user's view --------------------------------------------------------------------------


def test_help_lists_all_six_methods(capsys):
    code, out, _ = run_cli(["--help"], capsys)
    assert code == 0
    for name in ("LiDAR Iris", "Scan Context", "M2DP", "ESF", "GOSMatch", "ESM"):
        assert name in out


def test_descriptor_help_lists_the_valid_names(capsys):
    from lidar_iris_eval.descriptors import available_descriptors

    code, out, _ = run_cli(["eval", "--help"], capsys)
    flat = " ".join(out.split()).replace("- ", "-")  # click may wrap a name at its hyphen
    assert code == 0 and ", ".join(available_descriptors()) in flat


def test_frames_help_says_count_or_range(capsys):
    _, sim, _ = run_cli(["simulate", "--help"], capsys)
    _, ev, _ = run_cli(["eval", "--help"], capsys)
    assert "A COUNT" in sim and "RANGE" in ev


def test_extraction_bar_says_it_compiles_on_a_first_run(seq, tmp_path, capsys):
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.extract import extract
    from lidar_iris_eval.io import open_sequence

    extract(open_sequence(seq, frames="0:3"), get_descriptor("m2dp"), progress=True)
    assert "compiling kernels on a first run" in capsys.readouterr().err


def test_kitti_scan_without_labels_keeps_plain_points(tmp_path):
    """Guard: the rules accept what the test helpers write (small random scans)."""
    rng = np.random.default_rng(0)
    scans = [np.c_[rng.uniform(-20, 20, (200, 3)), np.zeros(200)] for _ in range(3)]
    root = write_kitti_sequence(tmp_path / "s", scans, np.tile(np.eye(4), (3, 1, 1)))
    from lidar_iris_eval.io import open_sequence

    assert len(open_sequence(root).scan(1).points) == 200
