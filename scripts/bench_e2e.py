#!/usr/bin/env python
"""End to end: simulate the full-resolution KITTI-00 world once, then time the full evaluation.

Usage::

    nice -n 19 python scripts/bench_e2e.py --world /work/k00 --json-out e2e.json
    python scripts/bench_e2e.py --world /tmp/w --frames 40 --azimuth-steps 128   # a tiny world
    python scripts/bench_e2e.py --world /tmp/t --world-preset tiny-mixed --azimuth-steps 128

Steps:

1. ``liris simulate WORLD --trajectory POSES --calib CALIB --azimuth-steps 2048``
   (KITTI 00: 4541 scans, ~12 GB, ~14 min on an idle 2-core machine), skipped
   when ``WORLD/manifest.json`` already describes the same simulation.
2. ``liris eval WORLD --protocol 1 --protocol 2 -d DESCRIPTORS --workers 2 --refine gicp``
   with a fresh, temporary descriptor cache and run folder, as a child process. The
   default ``-d`` is all seven methods: GOSMatch on the simulated labels, ESM and
   MapClosures on local maps from the ground-truth poses (``--odometry gt``).
   ``--world-preset`` simulates a built-in world (``liris simulate --world``) instead of
   the KITTI-00 trajectory; ``--refine none`` leaves registration out.

Recorded as JSON (``--json-out``, else stdout):

* ``wall_s`` and ``cpu_s`` (user + system of the evaluation and every process it
  waited for, from ``wait4``), the load average before and after;
* ``peak_rss_bytes``: the largest single process (``ru_maxrss`` of the children)
  and the largest sum over the whole process tree (sampled every 0.1 s from /proc);
* ``stages``: wall time of each progress stage as the child reports it on stderr
  (extraction per descriptor, matching per descriptor, registration per descriptor;
  protocols 1 and 2 share one matching pass, see ``match_source``), and from the run
  folder the summed per-scan read and extraction times per descriptor
  (``timing/<name>.csv``), the matching time per descriptor and protocol and the
  registration's ms per loop and per prepared scan (``metrics.json``);
* ``metrics``: each result's metrics without its timings, and their SHA-256, so
  two runs (or two versions of the code) can be checked for identical metrics
  (``--expect FILE`` compares with an earlier JSON and exits 1 on a difference).

On a shared machine every time here is contended: the load average says how much.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

SHARED = Path(__file__).resolve().parents[2] / "shared"
DEFAULT_POSES = SHARED / "data" / "kitti" / "poses" / "00.txt"
DEFAULT_CALIB = SHARED / "data" / "kitti" / "calib" / "00.txt"
#: all seven methods (GOSMatch on the simulated labels, ESM and MapClosures on local maps
#: from the ground-truth poses: ``--odometry gt``, the default)
DEFAULT_DESCRIPTORS = "lidar-iris,scan-context,m2dp,esf,gosmatch,esm,mapclosures"
#: result fields that are timings or run facts, not metrics
TIMING_FIELDS = {"extract_ms_per_scan", "match_ms_per_query", "match_us_per_pair",
                 "match_source", "registration_ms_per_loop", "registration_prepare_ms_per_scan",
                 "odometry_ms_per_scan"}
#: any other key naming a time (``*_ms``, ``*_ms_per_*``, ``*_s``) is a timing too
_TIMING_KEY = re.compile(r"(_ms|_us|_s|_seconds)(_per_[a-z]+)?$")
_BAR = re.compile(r"^\s*([A-Za-z0-9+_:.,-]+(?: matching| registration)?):\s")


def liris_command() -> list[str]:
    """``liris`` of this interpreter's environment (falls back to ``python -m``)."""
    exe = Path(sys.executable).with_name("liris")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "lidar_iris_eval"]


def simulate_if_needed(world: Path, args) -> dict:
    """Simulate the world unless ``manifest.json`` shows the same one; returns what was done."""
    manifest = world / "manifest.json"
    if manifest.is_file():
        cfg = json.loads(manifest.read_text()).get("config", {})
        same = cfg.get("azimuth_steps") == args.azimuth_steps and (
            args.frames is None or cfg.get("frames") == args.frames)
        if not same:
            sys.exit(f"bench_e2e: error: {world}: holds another simulation "
                     f"(azimuth_steps {cfg.get('azimuth_steps')}, frames {cfg.get('frames')}); "
                     "pick another --world")
        return {"reused": True, "seconds": 0.0, "frames": cfg.get("frames")}
    cmd = [*liris_command(), "simulate", str(world), "--azimuth-steps", str(args.azimuth_steps),
           "-q"]
    if args.world_preset is not None:
        cmd += ["--world", args.world_preset]
    elif args.trajectory is not None:
        cmd += ["--trajectory", str(args.trajectory)]
    if args.calib is not None and args.world_preset is None:
        cmd += ["--calib", str(args.calib)]
    if args.frames is not None:
        cmd += ["--frames", str(args.frames)]
    start = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    frames = json.loads(manifest.read_text()).get("config", {}).get("frames")
    return {"reused": False, "seconds": time.perf_counter() - start, "frames": frames,
            "command": cmd}


def _tree_rss(root: int) -> int:
    """Summed resident memory (bytes) of ``root`` and its descendants, from /proc."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
            pid, ppid = int(entry), int(fields[1])
            rss[pid] = int(fields[21]) * os.sysconf("SC_PAGE_SIZE")
            children.setdefault(ppid, []).append(pid)
        except (OSError, IndexError, ValueError):
            continue
    total, todo = 0, [root]
    while todo:
        pid = todo.pop()
        total += rss.get(pid, 0)
        todo.extend(children.get(pid, []))
    return total


def run_timed(cmd: list[str], env: dict) -> dict:
    """Run ``cmd``; wall, CPU (wait4), peak memory and stage times from its stderr bars."""
    stages: dict[str, list[float]] = {}
    tail: list[str] = []
    peak = [0]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    done = threading.Event()

    def read_stderr():
        buf = b""
        while chunk := proc.stderr.read1(65536):
            buf += chunk
            *parts, buf = re.split(rb"[\r\n]", buf)
            now = time.perf_counter() - start
            for raw in parts:
                line = raw.decode("utf-8", "replace")
                m = _BAR.match(line)
                if m and ("%|" in line or "it/s" in line or "scan" in line):
                    span = stages.setdefault(m.group(1), [now, now])
                    span[1] = now
                elif line.strip():
                    tail.append(line.strip())
                    del tail[:-20]

    def sample():
        while not done.wait(0.1):
            peak[0] = max(peak[0], _tree_rss(proc.pid))

    threads = [threading.Thread(target=read_stderr, daemon=True),
               threading.Thread(target=sample, daemon=True)]
    for t in threads:
        t.start()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    done.set()
    for t in threads:
        t.join(timeout=5)
    if proc.returncode != 0:
        sys.exit("bench_e2e: error: liris eval failed (exit "
                 f"{proc.returncode}): " + " | ".join(tail[-3:]))
    return {
        "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime,
        "user_s": usage.ru_utime, "system_s": usage.ru_stime,
        "peak_rss_bytes": {"max_single_process": usage.ru_maxrss * 1024,
                           "process_tree_sampled": peak[0]},
        "stage_wall_s": {name: span[1] - span[0] for name, span in stages.items()},
        "stage_spans_s": stages,
    }


def run_folder_stages(run: Path) -> dict:
    """Per-descriptor read / extraction sums (timing CSVs) and matching per protocol."""
    out: dict = {}
    for path in sorted((run / "timing").glob("*.csv")):
        with path.open() as f:
            rows = list(csv.DictReader(f))
        out[path.stem] = {
            "scans": len(rows),
            "read_s_sum": sum(float(r["read_s"]) for r in rows),
            "extract_cpu_s_sum": sum(float(r["extract_s"]) for r in rows),
        }
    metrics = json.loads((run / "metrics.json").read_text())
    for r in metrics["results"]:
        entry = out.setdefault(r["descriptor"], {})
        proto = {"match_source": r.get("match_source")}
        if r.get("match_ms_per_query") is not None:
            proto["match_ms_per_query"] = r["match_ms_per_query"]
            proto["match_s"] = r["match_ms_per_query"] * r.get("n_queries", 0) / 1e3
        if r.get("match_us_per_pair") is not None:
            proto["match_us_per_pair"] = r["match_us_per_pair"]
            proto["distance_evaluations"] = r.get("n_distance_evaluations")
            proto["match_s"] = r["match_us_per_pair"] * (r.get("n_distance_evaluations") or 0) / 1e6
        if r.get("registration_ms_per_loop") is not None:  # --refine: its own stage
            entry["registration"] = {
                "ms_per_loop": r["registration_ms_per_loop"],
                "prepare_ms_per_scan": r.get("registration_prepare_ms_per_scan"),
                "loops_registered": r.get("n_registered")}
        entry[f"protocol{r['protocol']}"] = proto
    return out


def metrics_only(run: Path) -> list[dict]:
    """Each result of ``metrics.json`` without its timing fields, in file order."""
    results = json.loads((run / "metrics.json").read_text())["results"]
    return [{k: v for k, v in r.items() if k not in TIMING_FIELDS and not _TIMING_KEY.search(k)}
            for r in results]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--world", type=Path, required=True,
                        help="simulated world folder (made once, then reused)")
    parser.add_argument("--trajectory", type=Path,
                        default=DEFAULT_POSES if DEFAULT_POSES.is_file() else None)
    parser.add_argument("--calib", type=Path,
                        default=DEFAULT_CALIB if DEFAULT_CALIB.is_file() else None)
    parser.add_argument("--world-preset", default=None,
                        help="a built-in world of liris simulate (instead of --trajectory)")
    parser.add_argument("--azimuth-steps", type=int, default=2048)
    parser.add_argument("--frames", type=int, default=None,
                        help="scans to simulate (default: every pose of the trajectory)")
    parser.add_argument("-d", "--descriptors", default=DEFAULT_DESCRIPTORS)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--refine", choices=("gicp", "icp", "none"), default="gicp",
                        help="register every protocol 1 match (timed as its own stage)")
    parser.add_argument("--json-out", type=Path, default=None)
    parser.add_argument("--keep", type=Path, default=None,
                        help="keep the run folder here (default: a temporary one, removed)")
    parser.add_argument("--expect", type=Path, default=None,
                        help="an earlier output of this script: exit 1 unless metrics match")
    args = parser.parse_args(argv)

    sim = simulate_if_needed(args.world, args)
    tmp = Path(tempfile.mkdtemp(prefix="liris-e2e-"))
    try:
        run = args.keep if args.keep is not None else tmp / "run"
        cmd = [*liris_command(), "eval", str(args.world), "--protocol", "1", "--protocol", "2",
               "-d", args.descriptors, "--workers", str(args.workers),
               "--cache-dir", str(tmp / "cache"), "--out", str(run), "--overwrite"]
        if args.refine != "none":
            cmd += ["--refine", args.refine]
        env = dict(os.environ)
        env.pop("LIRIS_CACHE_DIR", None)
        load_start = list(os.getloadavg())
        timed = run_timed(cmd, env)
        report = {
            "command": cmd, "simulation": sim, "cpus": os.cpu_count(),
            "load_average": {"start": load_start, "end": list(os.getloadavg())},
            **timed,
            "stages": run_folder_stages(run),
            "metrics": metrics_only(run),
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    blob = json.dumps(report["metrics"], sort_keys=True, allow_nan=True).encode()
    report["metrics_sha256"] = hashlib.sha256(blob).hexdigest()
    text = json.dumps(report, indent=2, allow_nan=True) + "\n"
    if args.json_out is not None:
        part = args.json_out.with_name(args.json_out.name + ".part")
        part.write_text(text)
        os.replace(part, args.json_out)
    else:
        sys.stdout.write(text)
    print(f"bench_e2e: wall {timed['wall_s']:.1f} s, CPU {timed['cpu_s']:.1f} s, peak "
          f"{timed['peak_rss_bytes']['process_tree_sampled'] / 2**30:.2f} GiB (tree), load "
          f"{load_start[0]:.2f} -> {report['load_average']['end'][0]:.2f}", file=sys.stderr)
    if args.expect is not None:
        before = json.loads(args.expect.read_text())["metrics_sha256"]
        same = before == report["metrics_sha256"]
        print(f"bench_e2e: metrics {'identical to' if same else 'DIFFER from'} {args.expect}",
              file=sys.stderr)
        return 0 if same else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
