#!/usr/bin/env python
"""Throughput of the LiDAR simulator on one core.

Times full-resolution scans (hdl64: 64 x 2048 rays, vlp16: 16 x 1800 rays) in
the ``small-mixed`` world, one scan per sampled frame including culling and
traffic, and an end-to-end ``tiny-mixed`` run written to a temporary folder.
Reports medians. Targets: >= 5 hdl64 scans/s, >= 30 vlp16 scans/s, tiny < 20 s.
``--workers-frames N`` also times ``small-mixed`` runs of N frames written with one
and with two worker processes (``liris simulate --workers``), interleaved, and checks
that both wrote the same bytes; the ratio only means something on an idle machine, so
the load average is printed beside it.

Usage: python scripts/bench_simulate.py [--scans N] [--repeats R] [--workers-frames N]
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import hashlib  # noqa: E402
import shutil  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from lidar_iris_eval.simulate import build_scenario, resolve_config, run_simulation  # noqa: E402
from lidar_iris_eval.simulate.sensors import simulate_scan  # noqa: E402


def bench_sensor(sensor: str, scans: int, repeats: int) -> dict:
    cfg = resolve_config("small-mixed", dict(sensor=sensor))
    cfg = dataclasses.replace(cfg, azimuth_steps=None)  # full resolution
    t0 = time.perf_counter()
    scen = build_scenario(cfg)
    build = time.perf_counter() - t0
    dirs = scen.sensor.grid.directions
    frames = np.linspace(0, len(scen.poses) - 1, scans).astype(int)
    per_scan, cpu, points = [], [], []
    for _ in range(repeats):
        for i in frames:
            t, c = time.perf_counter(), time.process_time()
            scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(int(i)),
                                 scen.poses[i], np.random.default_rng(int(i)), dirs)
            cpu.append(time.process_time() - c)
            per_scan.append(time.perf_counter() - t)
            points.append(len(scan.points))
    med = float(np.median(per_scan))
    return dict(sensor=sensor, rays=len(dirs), points=int(np.median(points)),
                median_s=med, scans_per_s=1.0 / med, cpu_s=float(np.median(cpu)),
                world_build_s=build)


def bench_tiny() -> tuple[float, float]:
    with tempfile.TemporaryDirectory() as tmp:
        t, c = time.perf_counter(), time.process_time()
        run_simulation(f"{tmp}/tiny", resolve_config("tiny-mixed", {}))
        return time.perf_counter() - t, time.process_time() - c


def tree_digest(folder: Path) -> str:
    """SHA-256 over every file's relative name and bytes."""
    digest = hashlib.sha256()
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        digest.update(path.relative_to(folder).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def bench_workers(frames: int, repeats: int) -> None:
    """Wall time of ``small-mixed`` at ``frames`` frames with 1 and 2 workers, interleaved."""
    cfg = resolve_config("small-mixed", dict(frames=frames))
    walls: dict[int, list[float]] = {1: [], 2: []}
    digests: dict[int, set[str]] = {1: set(), 2: set()}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(repeats):
            for workers in (1, 2):
                out = Path(tmp) / f"w{workers}-{r}"
                t = time.perf_counter()
                run_simulation(out, cfg, workers=workers)
                walls[workers].append(time.perf_counter() - t)
                digests[workers].add(tree_digest(out))
                shutil.rmtree(out)
    one, two = float(np.median(walls[1])), float(np.median(walls[2]))
    same = len(digests[1] | digests[2]) == 1
    print(f"small-mixed, {frames} frames written: --workers 1 median {one:.2f} s, --workers 2 "
          f"median {two:.2f} s ({repeats} interleaved runs each): {one / two:.2f}x; "
          f"files byte-identical: {'yes' if same else 'NO'}; load average "
          f"{os.getloadavg()[0]:.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=20, help="frames sampled along the route")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--workers-frames", type=int, default=0,
                    help="also time small-mixed runs of this many frames at --workers 1 and 2")
    args = ap.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f} (cores: {os.cpu_count()})")
    for sensor, target in (("hdl64", 5.0), ("vlp16", 30.0)):
        r = bench_sensor(sensor, args.scans, args.repeats)
        ok = "ok" if r["scans_per_s"] >= target else "BELOW TARGET"
        print(f"{sensor}: {r['rays']} rays, median {r['points']} points, "
              f"median {r['median_s'] * 1000:.1f} ms/scan = {r['scans_per_s']:.1f} scans/s "
              f"(target >= {target:g}: {ok}); CPU time {r['cpu_s'] * 1000:.1f} ms/scan = "
              f"{1 / r['cpu_s']:.1f} scans per CPU-second; world build {r['world_build_s']:.2f} s")
    wall, cpu = bench_tiny()
    print(f"tiny-mixed end to end (220 frames, written): {wall:.1f} s wall, {cpu:.1f} s CPU "
          "(target < 20 s)")
    if args.workers_frames > 0:
        bench_workers(args.workers_frames, args.repeats)
    print(f"load average at end: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
