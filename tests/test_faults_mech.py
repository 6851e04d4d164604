"""Issue 40: fault classes fixed in the shared mechanisms (one test each, all failed on ba544e2).

The CLI's last words (``liris: error:``, ``liris: interrupted``) stand on a
line of their own after progress bars; Ctrl-C ends any command with one line
and exit 130; pose readers refuse non-finite values; run readers check ranges.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from synthetic_loop import loop_sequence

LIRIS = [sys.executable, "-c", "from lidar_iris_eval.cli import main; main()"]


def liris(args, cwd: Path, **kwargs) -> subprocess.CompletedProcess:
    env = {**os.environ, "LIRIS_CACHE_DIR": str(cwd / "cache"), "OMP_NUM_THREADS": "1",
           "NUMBA_NUM_THREADS": "1"}
    return subprocess.run([*LIRIS, *map(str, args)], cwd=cwd, capture_output=True, text=True,
                          env=env, timeout=300, **kwargs)


@pytest.fixture(scope="module")
def seq(tmp_path_factory) -> Path:
    return loop_sequence(tmp_path_factory.mktemp("mech") / "seq", frames=30)


# ---- the error line starts on its own line, after the bar -------------------------------


def test_error_after_a_progress_bar_is_the_last_line_of_its_own(seq, tmp_path):
    import shutil

    bad = Path(shutil.copytree(seq, tmp_path / "bad"))
    (bad / "velodyne" / "000020.bin").write_bytes(b"\0" * 17)  # truncated, 20 scans in
    res = liris(["eval", bad, "-d", "m2dp", "--protocol", "1"], tmp_path)
    assert res.returncode == 2, res.stderr
    assert "m2dp:" in res.stderr  # a bar was drawn (the case this is about)
    last = res.stderr.split("\n")[-2] if res.stderr.endswith("\n") else res.stderr
    assert last.startswith("liris: error: "), repr(last[-300:])
    assert "000020.bin" in last
    assert res.stderr.endswith("\n")


# ---- Ctrl-C ---------------------------------------------------------------------------------


def interrupt(args, cwd: Path, after: float | str) -> tuple[int, str]:
    """Run liris, send SIGINT ``after`` seconds after start (or once ``after`` is on stderr)."""
    env = {**os.environ, "LIRIS_CACHE_DIR": str(cwd / "cache"), "OMP_NUM_THREADS": "1",
           "NUMBA_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([*LIRIS, *map(str, args)], cwd=cwd, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = b""
    if isinstance(after, str):
        deadline = time.monotonic() + 120
        while after.encode() not in err and time.monotonic() < deadline:
            chunk = os.read(proc.stderr.fileno(), 4096)
            if not chunk:
                break
            err += chunk
        assert after.encode() in err, f"never saw {after!r}: {err[-300:]!r}"
    else:
        time.sleep(after)
    assert proc.poll() is None, "finished before the interrupt"
    proc.send_signal(signal.SIGINT)
    _, rest = proc.communicate(timeout=120)
    return proc.returncode, (err + rest).decode(errors="replace")


def assert_interrupted(code: int, err: str) -> None:
    assert code == 130, err[-500:]
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err[-800:]
    lines = [line for line in err.split("\n") if line.strip()]
    assert lines[-1] == "liris: interrupted", repr(err[-300:])
    assert sum(line.startswith("liris: ") for line in lines) == 1, err[-500:]


def test_ctrl_c_during_simulate_is_one_line_and_leaves_nothing(tmp_path):
    code, err = interrupt(["simulate", "X", "--frames", "3000"], tmp_path, "simulate:")
    assert_interrupted(code, err)
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "cache") == []


def test_ctrl_c_during_start_up_is_one_line(tmp_path):
    # the commands take about a second to import; 0.6 s lands inside on this machine,
    # and any later moment must end the same way
    code, err = interrupt(["simulate", "X", "--frames", "3000"], tmp_path, 0.6)
    assert_interrupted(code, err)
    assert not (tmp_path / "X").exists()


def test_ctrl_c_during_eval_matching_is_one_line(seq, tmp_path):
    code, err = interrupt(["eval", seq, "-d", "esf", "--protocol", "2", "--out", "O"],
                          tmp_path, "esf:")
    assert_interrupted(code, err)
    assert not (tmp_path / "O").exists()


# ---- non-finite and non-rotation pose rows: one error naming file:line ------------------


def one_error(res: subprocess.CompletedProcess, *fragments: str) -> str:
    assert res.returncode == 2, res.stderr[-800:]
    assert "Traceback" not in res.stderr, res.stderr[-800:]
    errors = [line for line in res.stderr.splitlines() if line.startswith("liris: error:")]
    assert len(errors) == 1, res.stderr[-800:]
    for fragment in fragments:
        assert fragment in errors[0], (fragment, errors[0])
    return errors[0]


def nan_in_line(path: Path, index: int, field: int) -> int:
    """Put NaN in field ``field`` (comma-separated) of line ``index``; return its 1-based number."""
    lines = path.read_text().splitlines()
    parts = lines[index].split(",")
    parts[field] = "nan"
    lines[index] = ",".join(parts)
    path.write_text("\n".join(lines) + "\n")
    return index + 1


def test_nan_in_mulran_global_pose_names_the_line(tmp_path):
    from dataset_writers import loop_case, write_mulran

    seq = write_mulran(tmp_path, loop_case(1))
    number = nan_in_line(seq / "global_pose.csv", 3, 4)
    one_error(liris(["gt", seq], tmp_path), f"global_pose.csv:{number}", "NaN or inf")


def test_inf_in_oxford_ins_names_the_line(tmp_path):
    from dataset_writers import loop_case, write_oxford_bin

    run = write_oxford_bin(tmp_path, loop_case(2))
    ins = run / "gps" / "ins.csv"
    lines = ins.read_text().splitlines()
    parts = lines[3].split(",")
    parts[5] = "inf"  # northing
    lines[3] = ",".join(parts)
    ins.write_text("\n".join(lines) + "\n")
    one_error(liris(["gt", run], tmp_path), "ins.csv:4", "NaN or inf")


@pytest.mark.parametrize("writer", ["write_oxford_bin", "write_oxford_png"])
def test_nan_in_oxford_extrinsics_names_the_file(tmp_path, writer):
    """The raw (PNG) and the .bin layout share the INS and extrinsics readers."""
    import dataset_writers

    run = getattr(dataset_writers, writer)(tmp_path, dataset_writers.loop_case(2))
    run = run[0] if isinstance(run, tuple) else run
    (run / "extrinsics").mkdir(exist_ok=True)
    (run / "extrinsics" / "ins.txt").write_text("-1.7132 0.1181 nan -0.0125 0.0400 0.0050\n")
    one_error(liris(["gt", run], tmp_path), "ins.txt", "NaN or inf")


def trajectory(path: Path, bad: str | None) -> Path:
    lines = [f"1 0 0 {2.0 * i} 0 1 0 0 0 0 1 0" for i in range(8)]
    if bad is not None:
        lines[5] = bad
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("bad, fragment", [
    (" ".join(["nan"] * 12), "NaN or inf"),
    ("2 0 0 10 0 2 0 0 0 0 2 0", "not orthonormal"),  # was accepted, halving translations
])
def test_simulate_trajectory_row_is_checked_like_every_pose_file(tmp_path, bad, fragment):
    path = trajectory(tmp_path / "t.txt", bad)
    one_error(liris(["simulate", "-q", "X", "--trajectory", path], tmp_path),
              "t.txt:6", fragment)
    assert not (tmp_path / "X").exists()


# ---- TUM stamps must increase ------------------------------------------------------------


@pytest.mark.parametrize("swap", ["duplicate", "unsorted"])
def test_tum_stamps_out_of_order_name_the_first_bad_line(seq, tmp_path, swap):
    from scipy.spatial.transform import Rotation

    from lidar_iris_eval.io.poses import read_kitti_poses

    poses = read_kitti_poses(seq / "poses.txt")
    stamps = [0.1 * i for i in range(len(poses))]
    stamps[7] = stamps[6] if swap == "duplicate" else stamps[6] - 0.05
    lines = ["# timestamp x y z qx qy qz qw"]
    for t, pose in zip(stamps, poses, strict=True):
        q = Rotation.from_matrix(pose[:3, :3]).as_quat()
        lines.append(" ".join(f"{v:.9f}" for v in (t, *pose[:3, 3], *q)))
    (tmp_path / "t.tum").write_text("\n".join(lines) + "\n")
    # line 1 is the comment, so stamp 7 is on line 9
    one_error(liris(["gt", seq, "--poses", "t.tum"], tmp_path), "t.tum:9", "increase")


# ---- metrics.json ranges on read, empty runs -----------------------------------------------


@pytest.fixture(scope="module")
def run_dir(seq, tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("run")
    res = liris(["eval", seq, "-q", "-d", "m2dp", "--protocol", "2", "--out", root / "R"], root)
    assert res.returncode == 0, res.stderr
    return root / "R"


def edited_run(run_dir: Path, tmp_path: Path, key: str, value) -> Path:
    import json
    import shutil

    run = Path(shutil.copytree(run_dir, tmp_path / "B"))
    data = json.loads((run / "metrics.json").read_text())
    data["results"][0][key] = value
    (run / "metrics.json").write_text(json.dumps(data))
    return run


@pytest.mark.parametrize("key, value, fragment", [
    ("ap", 2.0, "outside [0, 1]"), ("f1_max", 1.5, "outside [0, 1]"),
    ("n_positives", -3, "negative"),
])
@pytest.mark.parametrize("command", ["show", "compare", "plot", "report"])
def test_out_of_range_metrics_are_named_on_read(run_dir, tmp_path, key, value, fragment,
                                                command):
    if command != "show" and key != "ap":
        pytest.skip("one key is enough for the other readers: they share load_run")
    run = edited_run(run_dir, tmp_path, key, value)
    argv = {"show": ["show", run], "compare": ["compare", run_dir, run],
            "plot": ["plot", run, "--out", tmp_path / "figs"],
            "report": ["report", run, "--out", tmp_path / "rep"]}[command]
    one_error(liris(argv, tmp_path), "metrics.json", f"results[0].{key}", fragment)


def test_show_of_an_empty_run_says_so(run_dir, tmp_path):
    import json
    import shutil

    run = Path(shutil.copytree(run_dir, tmp_path / "E"))
    data = json.loads((run / "metrics.json").read_text())
    data["results"] = []
    (run / "metrics.json").write_text(json.dumps(data))
    one_error(liris(["show", run], tmp_path), "metrics.json", "no results")


# ---- --export-loops when F1max is 0 ---------------------------------------------------------


@pytest.mark.parametrize("f1", [0.0, None])
def test_export_loops_with_f1max_zero_writes_none_and_warns(seq, tmp_path, f1):
    from lidar_iris_eval.errors import LirisWarning
    from lidar_iris_eval.evaluation.evaluate import Settings, evaluate, export_loops
    from lidar_iris_eval.io import open_sequence

    run = evaluate(open_sequence(seq), ["m2dp"], protocols=(1,), settings=Settings(exclude=5))
    p1 = run.results[0].protocol1
    # a threshold that accepts every match, as the first curve point does when F1max is 0
    p1.metrics["f1_threshold"] = float(np.nanmax(p1.matches.distance)) + 1.0
    assert (p1.matches.match >= 0).sum() > 0  # there are edges the export could write
    p1.metrics["f1_max"] = f1
    with pytest.warns(LirisWarning, match="F1max"):
        out = export_loops(run, tmp_path / "l.txt")
    assert [count for _, count in out.values()] == [0]


# ---- option contradictions and ranges --------------------------------------------------------


def test_seeds_beyond_32_bits_are_refused(seq, tmp_path):
    big = 2**64  # 18446744073709551616
    one_error(liris(["eval", seq, "-q", "-d", "m2dp", "--protocol", "1", "--seeds", f"1,{big}"],
                    tmp_path), "--seeds", str(big), "out of range")


def test_seed_at_the_32_bit_limit_is_accepted():
    from lidar_iris_eval.evaluation.seeds import parse_seeds

    assert parse_seeds(f"0,{2**32 - 1}") == (0, 2**32 - 1)


def test_bench_protocol_and_its_skip_are_contradictory(tmp_path):
    one_error(liris(["bench", "--protocol", "1", "--skip-protocol1"], tmp_path),
              "--skip-protocol1", "contradictory")


def test_foreign_warnings_are_one_line_without_source_paths(capsys):
    """NumPy's or matplotlib's warnings printed ``/…/metrics.py:218: …`` and the source line."""
    from lidar_iris_eval import cli as cli_module
    from lidar_iris_eval.errors import LirisWarning

    cli_module._show_warning(RuntimeWarning("invalid value\nencountered in divide"),
                             RuntimeWarning, "/site/numpy/core/_methods.py", 218)
    cli_module._show_warning(LirisWarning("no positives"), LirisWarning, "/x/metrics.py", 218)
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["liris: warning: RuntimeWarning: invalid value encountered in divide",
                     "liris: warning: no positives"]


def test_show_of_a_run_without_config_yaml_warns(run_dir, tmp_path):
    """It used to show liris's default conventions as if they were the run's, without a word."""
    import shutil

    run = Path(shutil.copytree(run_dir, tmp_path / "C"))
    (run / "config.yaml").unlink()
    res = liris(["show", run], tmp_path)
    assert res.returncode == 0, res.stderr
    warnings_ = [line for line in res.stderr.splitlines() if line.startswith("liris: warning:")]
    assert len(warnings_) == 1 and "config.yaml: missing" in warnings_[0], res.stderr
    assert "Traceback" not in res.stderr


def test_plot_of_an_iris_run_does_not_warn_about_parameters_nobody_set(seq, tmp_path):
    """config.yaml records every parameter; plot rebuilt Iris from it and warned
    "lidar-iris.shift_window: ignored" on every default run."""
    res = liris(["eval", seq, "-q", "-d", "lidar-iris", "--protocol", "1", "--out", tmp_path / "R"],
                tmp_path)
    assert res.returncode == 0, res.stderr
    res = liris(["plot", tmp_path / "R", "--out", tmp_path / "figs"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert "shift_window" not in res.stderr and "Traceback" not in res.stderr, res.stderr
