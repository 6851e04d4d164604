#!/usr/bin/env python3
"""Run bad-input and fault cases through the real ``liris`` CLI and count clean endings.

A case ends *cleanly* when ``liris`` either

* exits 0 and the case's own check of the result passes (the right number,
  the warning that qualifies it, the file it must write), or
* exits 2 with exactly one ``liris: error:`` line on stderr (warning lines
  allowed), no traceback, and the fragment the case expects in that line
  (the file or flag at fault).

Anything else (a traceback, exit 1, a silent wrong number, two error lines)
is counted as not clean and listed. Usage::

    python scripts/fault_battery.py [--keep DIR] [-k SUBSTRING] [-v]

Each case runs in a subprocess (``python -m lidar_iris_eval.cli``-style entry
through ``liris``), in a scratch folder holding one simulated sequence and
one finished run, so the battery needs nothing but this package.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

LIRIS = [sys.executable, "-c", "from lidar_iris_eval.cli import main; main()"]


@dataclass
class Result:
    code: int
    out: str
    err: str
    cwd: Path


@dataclass
class Case:
    name: str
    argv: list[str]
    setup: Callable[[Path], None] | None = None
    expect: str = "any"  # "error": must exit 2; "ok": must exit 0; "any": either, cleanly
    fragment: str = ""  # must appear in the error line
    check: Callable[[Result], str | None] | None = None  # message when the result is wrong
    env: dict[str, str] = field(default_factory=dict)
    # checked whatever the exit code (e.g. that the user's files are all still there)
    always: Callable[[Result], str | None] | None = None


def run(argv: list[str], cwd: Path, env: dict[str, str] | None = None,
        timeout: float = 300) -> Result:
    full_env = {**os.environ, "LIRIS_CACHE_DIR": str(cwd / "cache"), **(env or {})}
    try:
        proc = subprocess.run([*LIRIS, *argv], cwd=cwd, capture_output=True, text=True,
                              timeout=timeout, env=full_env)
    except subprocess.TimeoutExpired:
        return Result(-9, "", "TIMEOUT", cwd)
    return Result(proc.returncode, proc.stdout, proc.stderr, cwd)


def verdict(case: Case, res: Result) -> str | None:
    """None when the case ended cleanly, else why not."""
    why = _verdict(case, res)
    if why is None and case.always is not None:
        why = case.always(res)
    return why


def _verdict(case: Case, res: Result) -> str | None:
    if "Traceback" in res.err:
        return "traceback: " + res.err.strip().splitlines()[-1][:160]
    errors = [line for line in res.err.splitlines() if line.startswith("liris: error:")]
    if res.code == 2:
        if case.expect == "ok":
            return f"exit 2, expected success: {errors[:1]}"
        if len(errors) != 1:
            return f"exit 2 with {len(errors)} error lines"
        other = [line for line in res.err.splitlines()
                 if line.strip() and not line.startswith("liris: ")]
        if other:
            return f"stray stderr: {other[0][:120]}"
        if case.fragment and case.fragment not in errors[0]:
            return f"error does not name {case.fragment!r}: {errors[0][:160]}"
        return None
    if res.code == 0:
        if case.expect == "error":
            return "exit 0, expected an error (silently accepted)"
        if case.check is not None:
            return case.check(res)
        return None
    return f"exit {res.code}: {res.err.strip().splitlines()[-1][:160] if res.err.strip() else ''}"


# --- fixtures ------------------------------------------------------------------------


def make_base(root: Path) -> None:
    """A simulated sequence ``L`` and a finished scan-context run ``R``."""
    res = run(["simulate", "-q", "L"], root)
    assert res.code == 0, res.err
    res = run(["eval", "L", "-q", "-d", "scan-context", "--protocol", "1", "--protocol", "2",
               "--out", "R"], root)
    assert res.code == 0, res.err
    res = run(["eval", "L", "-q", "-d", "m2dp", "--protocol", "1", "--out", "RM"], root)
    assert res.code == 0, res.err


def copy_seq(name: str = "S", labels: bool = True) -> Callable[[Path], None]:
    def setup(cwd: Path) -> None:
        shutil.copytree(cwd.parent / "base" / "L", cwd / name)
        if not labels:
            shutil.rmtree(cwd / name / "labels")
    return setup


def copy_run(name: str = "R", src: str = "R") -> Callable[[Path], None]:
    def setup(cwd: Path) -> None:
        shutil.copytree(cwd.parent / "base" / src, cwd / name)
    return setup


def chain(*steps: Callable[[Path], None]) -> Callable[[Path], None]:
    def setup(cwd: Path) -> None:
        for step in steps:
            step(cwd)
    return setup


def edit_metrics(run_name: str, edit: Callable[[dict], None]) -> Callable[[Path], None]:
    def setup(cwd: Path) -> None:
        path = cwd / run_name / "metrics.json"
        data = json.loads(path.read_text())
        edit(data)
        path.write_text(json.dumps(data))
    return setup


def write(rel: str, data: bytes | str) -> Callable[[Path], None]:
    def setup(cwd: Path) -> None:
        path = cwd / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return setup


def scan_bytes(rel: str, make: Callable[[np.ndarray], bytes]) -> Callable[[Path], None]:
    """Replace the scan ``rel`` by ``make(original (N, 4) float32)``."""
    def setup(cwd: Path) -> None:
        path = cwd / rel
        data = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
        path.write_bytes(make(data))
    return setup


def edit_pose_line(rel: str, line_no: int, values: list[float]) -> Callable[[Path], None]:
    def setup(cwd: Path) -> None:
        path = cwd / rel
        lines = path.read_text().splitlines()
        lines[line_no] = " ".join(f"{v:.6e}" for v in values)
        path.write_text("\n".join(lines) + "\n")
    return setup


def first_seq_frames(n: int) -> list[str]:
    return ["--frames", f"0:{n}"]


def rng_bytes(n: int, seed: int = 0) -> bytes:
    return np.random.default_rng(seed).integers(0, 256, n, dtype=np.uint8).tobytes()


# --- checks on successful results -----------------------------------------------------


def stderr_has(text: str) -> Callable[[Result], str | None]:
    def check(res: Result) -> str | None:
        return None if text in res.err else f"stderr lacks {text!r}"
    return check


def stdout_has(text: str) -> Callable[[Result], str | None]:
    def check(res: Result) -> str | None:
        return None if text in res.out else f"stdout lacks {text!r}"
    return check


def metrics_of(run_dir: str, test: Callable[[dict], str | None]) -> Callable[[Result], str | None]:
    def check(res: Result) -> str | None:
        path = res.cwd / run_dir / "metrics.json"
        if not path.is_file():
            return f"no {path.name}"
        return test(json.loads(path.read_text()))
    return check


def no_temp_files(folder: str) -> Callable[[Result], str | None]:
    def check(res: Result) -> str | None:
        left = [p for p in (res.cwd / folder).rglob(".*") if ".tmp" in p.name]
        return f"temp files left: {left[:2]}" if left else None
    return check


def all_of(*checks: Callable[[Result], str | None]) -> Callable[[Result], str | None]:
    def check(res: Result) -> str | None:
        for c in checks:
            msg = c(res)
            if msg:
                return msg
        return None
    return check


# --- the cases ---------------------------------------------------------------------------


POSE_IDENTITY = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0]


def cases() -> list[Case]:
    c: list[Case] = []
    add = c.append
    seq = copy_seq()
    bare = copy_seq(labels=False)  # no labels: the scan's own checks must catch a bad scan
    quick = ["-q", "--frames", "0:80"]

    # scans: content plausibility
    add(Case("bin float64 file", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(bare, scan_bytes("S/velodyne/000005.bin",
                                   lambda d: d.astype(np.float64).tobytes())),
             "error", "000005.bin"))
    add(Case("bin float64 random values", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(bare, scan_bytes("S/velodyne/000005.bin",
                                   lambda d: (d.astype(np.float64) * 1.37 + 0.001).tobytes())),
             "error", "000005.bin"))
    add(Case("bin random bytes", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(bare, write("S/velodyne/000007.bin", rng_bytes(16 * 5000))),
             "error", "000007.bin"))
    add(Case("bin one point", ["eval", "S", *quick, "-d", "scan-context", "--protocol", "1"],
             chain(bare, scan_bytes("S/velodyne/000003.bin", lambda d: d[:1].tobytes())),
             "any", "000003.bin"))  # a one-point Scan Context is defined
    add(Case("bin one point m2dp", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(bare, scan_bytes("S/velodyne/000003.bin", lambda d: d[:1].tobytes())),
             "error", "000003.bin"))
    add(Case("bin one point esf", ["extract", "S", *quick, "-d", "esf"],
             chain(bare, scan_bytes("S/velodyne/000003.bin", lambda d: d[:1].tobytes())),
             "error", "000003.bin"))
    add(Case("bin huge coordinates", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(bare, scan_bytes("S/velodyne/000009.bin", lambda d: (d * 1e7).tobytes())),
             "error", "000009.bin"))
    add(Case("bin empty", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(bare, write("S/velodyne/000002.bin", b"")), "error", "000002.bin"))
    add(Case("bin truncated", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(bare, write("S/velodyne/000002.bin", b"\0" * 17)), "error", "000002.bin"))
    add(Case("bin all NaN", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(bare, scan_bytes("S/velodyne/000004.bin",
                                   lambda d: np.full_like(d, np.nan).tobytes())),
             "error", "000004.bin"))

    # PCD
    def pcd_seq(body: bytes, binary: bool = True) -> Callable[[Path], None]:
        def setup(cwd: Path) -> None:
            src = cwd.parent / "base" / "L"
            dst = cwd / "P"
            (dst / "scans").mkdir(parents=True)
            shutil.copy(src / "poses.txt", dst / "poses.txt")
            shutil.copy(src / "calib.txt", dst / "calib.txt")
            for i in range(40):
                data = np.fromfile(src / "velodyne" / f"{i:06d}.bin", np.float32).reshape(-1, 4)
                n = len(data)
                head = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\n"
                        f"TYPE F F F F\nCOUNT 1 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
                        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA binary\n").encode()
                payload = body if i == 6 and body else data.tobytes()
                if i == 6 and body:
                    payload = (body * (16 * n // len(body) + 1))[:16 * n]
                (dst / "scans" / f"{i:06d}.pcd").write_bytes(head + payload)
            lines = (src / "poses.txt").read_text().splitlines()[:40]
            (dst / "poses.txt").write_text("\n".join(lines) + "\n")
        return setup

    add(Case("pcd random body", ["eval", "P/scans", "-q", "-d", "m2dp", "--protocol", "1"],
             pcd_seq(rng_bytes(4096, 3)), "error", "000006.pcd"))
    add(Case("pcd good", ["eval", "P/scans", "-q", "-d", "m2dp", "--protocol", "1"],
             pcd_seq(b""), "ok"))

    # labels
    gos = ["eval", "S", "-q", "--frames", "0:60", "-d", "gosmatch", "--protocol", "1"]
    add(Case("label random bytes", gos,
             chain(seq, lambda cwd: (cwd / "S/labels/000012.label").write_bytes(
                 rng_bytes((cwd / "S/labels/000012.label").stat().st_size, 5))),
             "error", "000012.label"))
    add(Case("label empty", gos, chain(seq, write("S/labels/000012.label", b"")),
             "error", "000012.label"))

    def cache_then_edit(cwd: Path) -> None:
        copy_seq()(cwd)
        res = run(gos + ["--cache-dir", "c"], cwd)
        assert res.code == 0, res.err
        (cwd / "S/labels/000012.label").write_bytes(b"")

    add(Case("cache ignores labels", [*gos, "--cache-dir", "c"], cache_then_edit, "error",
             "000012.label"))

    # poses and calibration
    add(Case("pose zero rotation gt lidar", ["gt", "S", "--pose-frame", "lidar"],
             chain(seq, edit_pose_line("S/poses.txt", 10, [0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3])),
             "error", "poses.txt"))
    add(Case("pose zero rotation eval", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1"],
             chain(seq, edit_pose_line("S/poses.txt", 10, [0, 0, 0, 1, 0, 0, 0, 2, 0, 0, 0, 3])),
             "error", "poses.txt"))
    add(Case("pose scaled rotation", ["gt", "S"],
             chain(seq, edit_pose_line("S/poses.txt", 4, [2, 0, 0, 1, 0, 2, 0, 2, 0, 0, 2, 3])),
             "error", "poses.txt"))
    add(Case("pose NaN", ["gt", "S"],
             chain(seq, edit_pose_line("S/poses.txt", 4, [float("nan")] * 12)),
             "error", "poses.txt"))
    add(Case("pose 11 numbers", ["gt", "S"],
             chain(seq, edit_pose_line("S/poses.txt", 4, [1] * 11)), "error", "poses.txt"))
    add(Case("calib zero Tr gt lidar", ["gt", "S", "--pose-frame", "lidar"],
             chain(seq, write("S/calib.txt", "Tr: " + " ".join(["0"] * 12) + "\n")),
             "error", "calib.txt"))
    add(Case("calib zero Tr gt camera", ["gt", "S"],
             chain(seq, write("S/calib.txt", "Tr: " + " ".join(["0"] * 12) + "\n")),
             "error", "calib.txt"))
    add(Case("calib missing Tr", ["gt", "S", "--pose-frame", "lidar"],
             chain(seq, write("S/calib.txt", "P0: 1 2 3\n")), "error", "calib.txt"))
    add(Case("tum zero quaternion", ["gt", "S", "--poses", "t.txt"],
             chain(seq, write("t.txt", "".join(f"{i*0.1} {i} 0 0 0 0 0 0\n"
                                              for i in range(220)))),
             "error", "t.txt"))

    # --external
    def ext(name: str, array: np.ndarray | bytes) -> Callable[[Path], None]:
        def setup(cwd: Path) -> None:
            copy_seq()(cwd)
            if isinstance(array, bytes):
                (cwd / name).write_bytes(array)
            else:
                np.save(cwd / name, array)
        return setup

    ext_args = ["eval", "S", "-q", "--protocol", "1"]
    add(Case("external npz", [*ext_args, "--external", "net=f.npz"],
             chain(seq, lambda cwd: np.savez(cwd / "f.npz", a=np.zeros((220, 4)))),
             "error", "f.npz"))
    add(Case("external missing", [*ext_args, "--external", "net=nope.npy"], seq, "error",
             "nope.npy"))
    add(Case("external no name", [*ext_args, "--external", "f.npy"],
             ext("f.npy", np.zeros((220, 4))), "error", "--external"))
    add(Case("external wrong rows", [*ext_args, "--external", "net=f.npy"],
             ext("f.npy", np.random.default_rng(0).random((100, 8))), "error", "f.npy"))
    add(Case("external constant", [*ext_args, "--external", "net=f.npy"],
             ext("f.npy", np.ones((220, 8))), "ok",
             check=stderr_has("cannot mean much")))
    add(Case("external overflowing", [*ext_args, "--external", "net=f.npy"],
             ext("f.npy", np.random.default_rng(1).random((220, 8)) * 1e200), "any",
             check=stderr_has("cannot mean much")))
    add(Case("external NaN", [*ext_args, "--external", "net=f.npy"],
             ext("f.npy", np.full((220, 8), np.nan)), "error", "f.npy"))
    add(Case("external garbage bytes", [*ext_args, "--external", "net=f.npy"],
             ext("f.npy", rng_bytes(1000)), "error", "f.npy"))

    # --param
    sc = ["eval", "S", *quick, "--protocol", "1"]
    add(Case("param empty value", [*sc, "-d", "lidar-iris", "--param", "lidar-iris.rings="],
             seq, "error", "rings"))
    add(Case("param huge value", [*sc, "-d", "lidar-iris", "--param",
                                  "lidar-iris.rings=100000000000"], seq, "error", "rings"))
    add(Case("param negative", [*sc, "-d", "scan-context", "--param",
                                "scan-context.rings=-3"], seq, "error", "rings"))
    add(Case("param unknown key", [*sc, "-d", "m2dp", "--param", "m2dp.nope=3"], seq, "error",
             "nope"))
    add(Case("param no dot", [*sc, "-d", "m2dp", "--param", "rings=3"], seq, "error",
             "--param"))
    add(Case("param text for int", [*sc, "-d", "m2dp", "--param", "m2dp.seed=abc"], seq,
             "error", "seed"))
    add(Case("descriptor unknown", [*sc, "-d", "nope"], seq, "error", "nope"))

    # --config
    def cfg(text: str) -> Callable[[Path], None]:
        return chain(seq, write("c.yaml", text))

    cfg_args = ["eval", "S", "-q", "-d", "m2dp", "--protocol", "1", "--frames", "0:80",
                "--config", "c.yaml"]
    add(Case("config exclude int", cfg_args, cfg("exclude: 30\n"), "any"))
    add(Case("config descriptors string", ["eval", "S", "-q", "--frames", "0:80",
                                           "--protocol", "1", "--config", "c.yaml"],
             cfg("descriptors: m2dp\n"), "any"))
    add(Case("config unknown key", cfg_args, cfg("radious: 5\n"), "error", "radious"))
    add(Case("config unknown nested", cfg_args, cfg("engine: {scheduler: foo}\n"), "error",
             "scheduler"))
    add(Case("config not mapping", cfg_args, cfg("- 1\n- 2\n"), "error", "c.yaml"))
    add(Case("config bad yaml", cfg_args, cfg("a: [1, 2\n"), "error", "c.yaml"))
    add(Case("config radius text", cfg_args, cfg("radius: far\n"), "error", "radius"))

    # metrics.json read by compare / plot / show / report
    def bad_metrics(edit: Callable[[dict], None]) -> Callable[[Path], None]:
        return chain(copy_run("A"), copy_run("B"), edit_metrics("B", edit))

    def set_row(key: str, value: object) -> Callable[[dict], None]:
        def edit(d: dict) -> None:
            d["results"][0][key] = value
        return edit

    for key, value in (("ap", "high"), ("protocol", "one")):
        for cmd in ("compare", "plot", "show", "report"):
            argv = {"compare": ["compare", "A", "B"], "plot": ["plot", "B", "--out", "figs"],
                    "show": ["show", "B"], "report": ["report", "B", "--out", "rep"]}[cmd]
            add(Case(f"{cmd} metrics {key}={value}", argv, bad_metrics(set_row(key, value)),
                     "error", "metrics.json"))
    add(Case("compare metrics not json", ["compare", "A", "B"],
             chain(copy_run("A"), copy_run("B"), write("B/metrics.json", "{")),
             "error", "metrics.json"))
    add(Case("compare results not list", ["compare", "A", "B"],
             bad_metrics(lambda d: d.__setitem__("results", {"a": 1})), "error", "metrics.json"))

    def count_check(res: Result) -> str | None:
        # scan-context (P1, P2) vs m2dp (P1): no descriptor in common, so 0 comparable values
        for line in res.out.splitlines():
            if "differ" in line and "metric value" in line:
                n = int(line.split()[0])
                return None if n == 0 else f"reports {n} differing values with 0 comparable"
        return "no count line"

    add(Case("compare counts only comparable", ["compare", "A", "B"],
             chain(copy_run("A", "R"), copy_run("B", "RM")), "ok", check=count_check))
    add(Case("compare plot bad suffix", ["compare", "A", "B", "--plot", "x.jpg2"],
             chain(copy_run("A"), copy_run("B")), "error", "x.jpg2"))
    add(Case("compare plot good", ["compare", "A", "B", "--plot", "x.png"],
             chain(copy_run("A"), copy_run("B")), "ok",
             check=lambda r: None if (r.cwd / "x.png").is_file() else "no x.png"))
    add(Case("compare one run", ["compare", "A"], copy_run("A"), "error", "compare"))
    add(Case("compare missing", ["compare", "A", "nope"], copy_run("A"), "error", "nope"))
    add(Case("plot bad format", ["plot", "A", "--out", "figs", "--format", "jpg2"],
             copy_run("A"), "error", "jpg2"))

    # simulate
    add(Case("simulate azimuth huge", ["simulate", "-q", "X", "--azimuth-steps", "100000000"],
             None, "error", "--azimuth-steps",
             ))
    add(Case("simulate azimuth huge leaves nothing",
             ["simulate", "-q", "X", "--azimuth-steps", "100000000"], None, "error",
             "--azimuth-steps"))
    add(Case("simulate seed -1", ["simulate", "-q", "X", "--seed", "-1", "--frames", "20"],
             None, "any"))
    add(Case("simulate seed huge", ["simulate", "-q", "X", "--seed", str(2**70),
                                     "--frames", "20"], None, "any"))
    add(Case("simulate frames 0", ["simulate", "-q", "X", "--frames", "0"], None, "error",
             "--frames"))
    add(Case("simulate frames -5", ["simulate", "-q", "X", "--frames", "-5"], None, "error",
             "--frames"))
    add(Case("simulate azimuth 0", ["simulate", "-q", "X", "--azimuth-steps", "0"], None,
             "error", "--azimuth-steps"))
    add(Case("simulate out is file", ["simulate", "-q", "X"], write("X", "x"), "error", "X"))

    # workers, bench, misc flags
    add(Case("workers 1000", ["extract", "S", "-q", "--frames", "0:40", "-d", "m2dp",
                              "--workers", "1000"], seq, "ok",
             check=stderr_has("--workers")))
    add(Case("workers 0", ["extract", "S", "-q", "--frames", "0:40", "-d", "m2dp",
                           "--workers", "0"], seq, "error", "--workers"))
    add(Case("bench world nope", ["bench", "--world", "nope"], None, "error", "--world"))
    add(Case("frames bad range", ["gt", "S", "--frames", "5:2"], seq, "error", "--frames"))
    add(Case("frames beyond", ["gt", "S", "--frames", "300:400"], seq, "error", "--frames"))
    add(Case("radius negative", ["gt", "S", "--radius", "-1"], seq, "error", "--radius"))
    add(Case("radius nan", ["gt", "S", "--radius", "nan"], seq, "error", "--radius"))
    add(Case("exclude bad", ["gt", "S", "--exclude", "abc"], seq, "error", "--exclude"))
    add(Case("seq missing", ["gt", "nope"], None, "error", "nope"))

    def p2_check(d: dict) -> str | None:
        for row in d["results"]:
            if row["protocol"] == 2:
                for key in ("match_us_per_pair", "match_ms_per_pair", "match_time"):
                    if key in row and row[key] is not None:
                        return f"{key} = {row[key]} for 0 pairs"
        return None

    add(Case("protocol 2 one frame", ["eval", "S", "-q", "--frames", "0:1", "-d", "m2dp",
                                      "--protocol", "2", "--out", "O"], seq, "any",
             check=metrics_of("O", p2_check)))

    def warn_kept(d: dict) -> str | None:
        text = json.dumps(d)
        return None if "cannot mean much" in text else "degenerate warning not in metrics.json"

    add(Case("warning stored in run", [*ext_args, "--external", "net=f.npy", "--out", "O"],
             ext("f.npy", np.ones((220, 8))), "ok", check=metrics_of("O", warn_kept)))

    def show_warning(cwd: Path) -> None:
        ext("f.npy", np.ones((220, 8)))(cwd)
        res = run([*ext_args, "--external", "net=f.npy", "--out", "O"], cwd)
        assert res.code == 0, res.err

    add(Case("show prints stored warning", ["show", "O"], show_warning, "ok",
             check=lambda r: None if "cannot mean much" in r.out else "no warning shown"))
    add(Case("compare prints stored warning", ["compare", "O", "R"],
             chain(show_warning, copy_run("R")), "ok",
             check=lambda r: None if "cannot mean much" in r.out else "no warning shown"))

    # exports
    add(Case("export npy mode", ["extract", "S", *quick, "-d", "m2dp", "--export-npy", "E"],
             seq, "ok",
             check=lambda r: None if all(
                 (p.stat().st_mode & 0o777) == 0o644 for p in (r.cwd / "E").glob("*.npy"))
             else "export not 0644"))
    add(Case("export loops bad suffix", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1",
                                         "--export-loops", "l.xyz"], seq, "error",
             "--export-loops"))

    # issue 40: finite and orthonormal trajectories, stamp order, ranges on read, seeds
    def traj(bad: str) -> Callable[[Path], None]:
        lines = [f"1 0 0 {2.0 * i} 0 1 0 0 0 0 1 0" for i in range(8)]
        lines[5] = bad
        return write("t.txt", "\n".join(lines) + "\n")

    add(Case("simulate trajectory NaN row", ["simulate", "-q", "X", "--trajectory", "t.txt"],
             traj(" ".join(["nan"] * 12)), "error", "t.txt:6"))
    add(Case("simulate trajectory scaled rotation",
             ["simulate", "-q", "X", "--trajectory", "t.txt"],
             traj("2 0 0 10 0 2 0 0 0 0 2 0"), "error", "t.txt:6"))

    def tum(stamps: list[float]) -> Callable[[Path], None]:
        def setup(cwd: Path) -> None:
            copy_seq()(cwd)
            n = len((cwd / "S/poses.txt").read_text().splitlines())
            times = [0.1 * i for i in range(n)]
            times[10:10 + len(stamps)] = stamps
            (cwd / "t.tum").write_text("".join(f"{t:.6f} {i} 0 0 0 0 0 1\n"
                                               for i, t in enumerate(times)))
        return setup

    add(Case("tum duplicate stamp", ["gt", "S", "--poses", "t.tum"], tum([0.9]), "error",
             "t.tum:11"))
    add(Case("tum unsorted stamps", ["gt", "S", "--poses", "t.tum"], tum([0.5]), "error",
             "t.tum:11"))
    for key, value in (("ap", 2.0), ("f1_max", 1.5), ("n_positives", -3)):
        for cmd in ("compare", "plot", "show", "report"):
            argv = {"compare": ["compare", "A", "B"], "plot": ["plot", "B", "--out", "figs"],
                    "show": ["show", "B"], "report": ["report", "B", "--out", "rep"]}[cmd]
            add(Case(f"{cmd} metrics {key}={value} out of range", argv,
                     bad_metrics(set_row(key, value)), "error", key))
    add(Case("show empty results", ["show", "B"],
             bad_metrics(lambda d: d.__setitem__("results", [])), "error", "no results"))
    add(Case("seeds beyond 64 bits", ["eval", "S", *quick, "-d", "m2dp", "--protocol", "1",
                                      "--seeds", "18446744073709551616"], seq, "error",
             "--seeds"))
    add(Case("bench protocol and its skip", ["bench", "--protocol", "1", "--skip-protocol1"],
             None, "error", "--skip-protocol1"))

    # issue 40, minor cases: listings, counts, times, foreign warnings, a run without config.yaml
    def link_loop(cwd: Path) -> None:
        copy_seq()(cwd)
        names = sorted((cwd / "S/velodyne").iterdir())
        loop = cwd / "S/velodyne" / f"{int(names[-1].stem) + 1:06d}.bin"
        loop.symlink_to(loop)

    add(Case("scan is a symlink loop", ["gt", "S"], link_loop, "error", "symbolic-link loop"))

    def missing_scan(cwd: Path) -> None:
        copy_seq()(cwd)
        (cwd / "S/velodyne/000007.bin").unlink()

    add(Case("count error names the missing scan", ["gt", "S"], missing_scan, "error",
             "no scan numbered 000007"))

    def nan_time(cwd: Path) -> None:
        copy_seq()(cwd)
        lines = (cwd / "S/times.txt").read_text().splitlines()
        lines[4] = "nan"
        (cwd / "S/times.txt").write_text("\n".join(lines) + "\n")

    add(Case("NaN scan time", ["gt", "S"], nan_time, "error", "times.txt: time 5 is nan"))

    def without_config(cwd: Path) -> None:
        copy_run("B")(cwd)
        (cwd / "B/config.yaml").unlink()

    add(Case("show of a run without config.yaml warns", ["show", "B"], without_config, "ok",
             check=stderr_has("config.yaml: missing")))

    # help for a new user
    def lists_all(res: Result) -> str | None:
        names = ("LiDAR Iris", "Scan Context", "M2DP", "ESF", "GOSMatch", "ESM")
        missing = [n for n in names if n not in res.out]
        return f"--help lacks {missing}" if missing else None

    add(Case("help lists six methods", ["--help"], None, "ok", check=lists_all))

    def d_lists(res: Result) -> str | None:
        flat = " ".join(res.out.split())
        names = ("lidar-iris", "scan-context", "m2dp", "esf", "gosmatch", "esm")
        missing = [n for n in names if n not in flat]
        return f"-d help lacks {missing}" if missing else None

    add(Case("eval -d help lists names", ["eval", "--help"], None, "ok", check=d_lists))
    add(Case("frames help says range", ["simulate", "--help"], None, "ok",
             check=lambda r: None if "count" in " ".join(r.out.split()).lower()
             else "simulate --frames help does not say it is a count"))
    return c


def digest_tree(root: Path) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes()
            for p in sorted(root.rglob("*")) if p.is_file()}


def unchanged(folder: str) -> tuple[Callable[[Path], None], Callable[[Result], str | None]]:
    """A setup step that records ``folder``'s bytes and a check that they are all still there."""
    before: dict[str, bytes] = {}

    def record(cwd: Path) -> None:
        before.clear()
        before.update(digest_tree(cwd / folder))

    def check(res: Result) -> str | None:
        after = digest_tree(res.cwd / folder) if (res.cwd / folder).exists() else {}
        lost = sorted(k for k in before if after.get(k) != before[k])
        return f"{folder}: {len(lost)} files lost or changed ({lost[:2]})" if lost else None

    return record, check


def ownership_cases() -> list[Case]:
    """Issue 40: --overwrite only replaces what liris wrote; nothing of the user's is lost."""
    c: list[Case] = []
    quick = ["-q", "--frames", "0:80", "-d", "m2dp", "--protocol", "1"]
    record, same = unchanged("S")
    c.append(Case("eval --out the input --overwrite", ["eval", "S", *quick, "--out", "S",
                                                       "--overwrite"],
                  chain(copy_seq(), record), "error", "not a folder liris wrote", always=same))
    record, same = unchanged(".")
    c.append(Case("eval --out the parent of the input --overwrite",
                  ["eval", "S", *quick, "--out", ".", "--overwrite"],
                  chain(copy_seq(), record), "error", "not a folder liris wrote", always=same))
    record, same = unchanged("R")
    c.append(Case("eval --overwrite a run holding a user file",
                  ["eval", "S", *quick, "--out", "R", "--overwrite"],
                  chain(copy_seq(), copy_run(), write("R/notes.txt", "mine\n"), record),
                  "error", "notes.txt", always=same))
    record, same = unchanged("rep")
    c.append(Case("report --overwrite a folder of the user's",
                  ["report", "R", "--out", "rep", "--overwrite"],
                  chain(copy_run(), write("rep/slides.pdf", b"%PDF mine"), record),
                  "error", "not a folder liris wrote", always=same))
    record, same = unchanged("keep")
    c.append(Case("export-loops onto an existing file",
                  ["eval", "S", *quick, "--out", "O", "--export-loops", "keep/l.g2o"],
                  chain(copy_seq(), write("keep/l.g2o", "# mine\n"), record),
                  "error", "--overwrite", always=same))
    record, same = unchanged("S")
    c.append(Case("export-loops onto an input file with --overwrite",
                  ["eval", "S", *quick, "--out", "O", "--export-loops", "S/poses.txt",
                   "--overwrite"], chain(copy_seq(), record), "error", "part of the input",
                  always=same))
    record, same = unchanged("keep")
    c.append(Case("compare --plot onto an existing image",
                  ["compare", "R", "R2", "--plot", "keep/x.png"],
                  chain(copy_run(), copy_run("R2"), write("keep/x.png", b"mine"), record),
                  "error", "--overwrite", always=same))
    record, same = unchanged("S")
    c.append(Case("simulate --overwrite a sequence with a user file",
                  ["simulate", "S", "-q", "--frames", "3", "--overwrite"],
                  chain(copy_seq(), write("S/velodyne/readme.md", "mine"), record),
                  "error", "velodyne/readme.md", always=same))
    return c


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-k", default="", help="run only cases whose name contains this")
    parser.add_argument("--keep", type=Path, default=None, help="scratch folder to keep")
    parser.add_argument("-v", action="store_true", help="print every case")
    parser.add_argument("--json", type=Path, default=None, help="write the verdicts here")
    args = parser.parse_args()
    root = Path(tempfile.mkdtemp(prefix="liris-faults-")) if args.keep is None else args.keep
    root.mkdir(parents=True, exist_ok=True)
    base = root / "base"
    if not (base / "R" / "metrics.json").is_file():
        base.mkdir(exist_ok=True)
        make_base(base)
    selected = [case for case in cases() + ownership_cases() if args.k in case.name]
    failures: dict[str, str] = {}
    for k, case in enumerate(selected):
        cwd = root / f"case{k:03d}"
        shutil.rmtree(cwd, ignore_errors=True)
        cwd.mkdir()
        try:
            if case.setup is not None:
                case.setup(cwd)
            res = run(case.argv, cwd, case.env)
            why = verdict(case, res)
            if why is None and case.name == "simulate azimuth huge leaves nothing" and (
                    cwd / "X").exists():
                why = "left a folder X behind"
        except AssertionError as err:
            why = f"setup failed: {err}"
        if why is not None:
            failures[case.name] = why
        if args.v or why is not None:
            print(f"{'FAIL' if why else 'ok  '} {case.name}: {why or ''}", flush=True)
        if why is None:
            shutil.rmtree(cwd, ignore_errors=True)
    clean = len(selected) - len(failures)
    print(f"{clean} of {len(selected)} cases ended cleanly")
    if args.json is not None:
        args.json.write_text(json.dumps({"clean": clean, "total": len(selected),
                                         "failures": failures}, indent=2) + "\n")
    if args.keep is None:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if not failures else 1


if __name__ == "__main__":
    sys.exit(main())
