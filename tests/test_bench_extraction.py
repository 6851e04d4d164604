"""liris bench's per-scan timings: C++ ratios only from drivers timed in the same run.

A fake driver (a Python script following the documented contract) prints
known per-scan times; the ratios must be formed from exactly those numbers.
Without a driver, no ratio may appear anywhere, and the remembered figures
are labelled as published figures from another machine.
"""

from __future__ import annotations

import json
import stat
import sys
import textwrap

import numpy as np
import pytest
from click.testing import CliRunner

from lidar_iris_eval.bench.drivers import find_drivers, parse_output, run_driver
from lidar_iris_eval.bench.extraction import (
    PUBLISHED_LABEL,
    cpp_heading,
    cpp_rows,
    measure_extraction,
)
from lidar_iris_eval.cli import cli
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.errors import LirisError

#: the fake driver: reads the list, reads each scan, prints 10 ms x (line number)
#: and one pair line of 40 us; with FAIL in its name it exits 3
FAKE_DRIVER = """\
    #!{python}
    import sys
    import numpy as np
    paths = [p.strip() for p in open(sys.argv[1]) if p.strip()]
    if "fail" in sys.argv[0]:
        print("boom: cannot load", file=sys.stderr)
        sys.exit(3)
    print("# fake driver, contract of lidar_iris_eval/bench/drivers.py")
    for i, p in enumerate(paths):
        pts = np.fromfile(p, dtype=np.float32).reshape(-1, 4)
        print("extract", p, 10.0 * (i + 1))
    if len(paths) > 1:
        print("pair", paths[0], paths[1], 40.0)
"""


def _scans(tmp_path, count=3, points=3000):
    rng = np.random.default_rng(0)
    folder = tmp_path / "scans"
    folder.mkdir()
    paths, scans = [], []
    for i in range(count):
        xyz = np.c_[rng.uniform(-30, 30, (points, 2)), rng.uniform(-1.7, 3, points)]
        cloud = np.c_[xyz, np.zeros(points)].astype(np.float32)
        path = folder / f"{i:06d}.bin"
        cloud.tofile(path)
        paths.append(str(path))
        scans.append(cloud[:, :3].copy())
    return folder, paths, scans


def _driver(folder, name):
    folder.mkdir(exist_ok=True)
    path = folder / name
    path.write_text(textwrap.dedent(FAKE_DRIVER).format(python=sys.executable))
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


def _keys(obj):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield k
            yield from _keys(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _keys(v)


def test_ratios_come_from_the_driver_timed_in_this_run(tmp_path):
    _, paths, scans = _scans(tmp_path)
    drivers = find_drivers(_driver(tmp_path / "cpp", "scan-context").parent)
    assert set(drivers) == {"scan-context"}
    descs = [get_descriptor("scan-context", preset="reference"),
             get_descriptor("m2dp", preset="reference")]
    result = measure_extraction(descs, scans, rounds=2, pair_repeats=12, isolate=False,
                                drivers=drivers, scan_paths=paths)
    sc = result["descriptors"]["scan-context:reference"]
    cpp = sc["cpp"]
    assert cpp["extract_ms_per_scan"] == [10.0, 20.0, 30.0]
    assert len(cpp["driver_wall_s_per_round"]) == 2  # run once per round
    ours = np.asarray(sc["extract_ms_per_scan"])
    assert cpp["extract_ratio"] == pytest.approx(np.median(ours / [10.0, 20.0, 30.0]))
    assert cpp["pair_us"] == 40.0 and cpp["pair_ratio"] == pytest.approx(sc["pair_us"] / 40.0)
    # no driver for M2DP: no ratio, shown as '-'
    assert result["descriptors"]["m2dp:reference"]["cpp"] is None
    rows = {r["descriptor"]: r for r in cpp_rows(result)}
    assert rows["m2dp:reference"]["extract_x_C++"] == "-"
    assert rows["scan-context:reference"]["C++_ms"] == "20.00"
    assert "timed in this run" in cpp_heading(result)


def test_without_drivers_no_ratio_anywhere_and_figures_are_labelled(tmp_path):
    _, _, scans = _scans(tmp_path, count=2)
    descs = [get_descriptor("scan-context", preset="reference")]
    result = measure_extraction(descs, scans, rounds=1, pair_repeats=4, isolate=False)
    assert not [k for k in _keys(result) if "ratio" in k]
    entry = result["descriptors"]["scan-context:reference"]
    assert entry["cpp"] is None and entry["published"]["label"] == PUBLISHED_LABEL
    (row,) = cpp_rows(result)
    assert not [k for k in row if "x_C++" in k]  # no ratio column
    assert set(row) >= {"published_C++_ms", "published_C++_us"}
    assert PUBLISHED_LABEL in cpp_heading(result) and "not a ratio" in cpp_heading(result)


def test_driver_output_is_checked(tmp_path):
    paths = ["/a.bin", "/b.bin"]
    good = parse_output("# hello\nextract /a.bin 1.5\nnoise\nextract /b.bin 2\npair /a.bin "
                        "/b.bin 7\n", paths, "drv")
    assert good == {"extract_ms": [1.5, 2.0], "pair_us": [7.0]}
    for text, problem in [
        ("extract /a.bin 1\n", "no 'extract' line for 1 of 2 scans (first: /b.bin)"),
        ("extract /a.bin fast\nextract /b.bin 1\n", "line 1: expected 'extract <path> <ms>'"),
        ("extract /a.bin -1\nextract /b.bin 1\n", "not a finite non-negative"),
        ("extract /a.bin 1\nextract /a.bin 2\nextract /b.bin 1\n", "second time for /a.bin"),
        ("extract /a.bin 1\nextract /b.bin 1\npair /a.bin 3\n", "line 3: expected 'pair"),
    ]:
        with pytest.raises(LirisError, match="drv: .*" + problem.replace("(", r"\(")
                           .replace(")", r"\)")):
            parse_output(text, paths, "drv")


def test_failing_driver_and_bad_folder_are_one_line_errors(tmp_path):
    _, paths, _ = _scans(tmp_path, count=1)
    failing = _driver(tmp_path / "cpp", "fail-driver")
    with pytest.raises(LirisError, match=r"driver failed \(exit 3\): boom: cannot load"):
        run_driver(failing, paths)
    with pytest.raises(LirisError, match="no driver: expected an executable named one of"):
        find_drivers(tmp_path / "cpp")  # only 'fail-driver' there
    runner = CliRunner()
    result = runner.invoke(cli, ["bench", "--cpp", str(tmp_path / "missing"), "-q",
                                 "--work-dir", str(tmp_path / "work")])
    assert isinstance(result.exception, LirisError)  # the entry point prints it, exit 2
    assert str(result.exception).endswith("missing: no such folder (--cpp)")
    assert not (tmp_path / "work").exists()  # refused before simulating anything


def test_cli_cpp_table_is_measured_in_the_run(tmp_path):
    folder, paths, _ = _scans(tmp_path, count=2, points=2000)
    _driver(tmp_path / "cpp", "m2dp")
    seq = tmp_path / "seq"
    runner = CliRunner()
    sim = runner.invoke(cli, ["simulate", str(seq), "--frames", "4", "--azimuth-steps", "64",
                              "-q"])
    assert sim.exit_code == 0, sim.output
    args = ["bench", "--sequence", str(seq), "--work-dir", str(tmp_path / "work"), "-d", "m2dp",
            "-q", "--skip-protocol1", "--skip-protocol2", "--loop-pairs", "0",
            "--kernel-queries", "2", "--in-process", "--cpp-scans", "2", "--scans", str(folder),
            "--cpp", str(tmp_path / "cpp"), "--json-out", str(tmp_path / "r.json")]
    result = runner.invoke(cli, args)
    assert result.exit_code == 0, result.output
    assert "timed in this run by the --cpp drivers" in result.output
    report = json.loads((tmp_path / "r.json").read_text())
    cpp = report["cpp_comparison"]["descriptors"]["m2dp:reference"]["cpp"]
    assert cpp["extract_ms_per_scan"] == [10.0, 20.0]
    # and without --cpp the same table carries no ratio
    plain = runner.invoke(cli, args[:-4] + ["--json-out", str(tmp_path / "p.json")])
    assert plain.exit_code == 0, plain.output
    assert PUBLISHED_LABEL in plain.output and "x_C++" not in plain.output
    assert "ratio" not in json.dumps(json.loads((tmp_path / "p.json").read_text())
                                     ["cpp_comparison"])
