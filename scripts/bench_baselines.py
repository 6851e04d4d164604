#!/usr/bin/env python
"""Extraction time of the M2DP and ESF baselines per ~120k-point scan, on one core.

Usage::

    python scripts/bench_baselines.py [--repeats 15] [--scans DIR] [--noise] [--json FILE]

It pins the process to one CPU and one BLAS/OpenMP thread *before* importing
NumPy, then times ``compute`` on the real KITTI scans under ``--scans``
(default: ``../shared/data/kitti/samples/00/velodyne`` next to the repository)
or, if absent, on a synthetic 120k-point cloud. Each scan is computed once
to warm up, then ``--repeats`` times; the figure reported is the median over
all timed runs, with the ratio to a fixed NumPy calibration workload timed in
the same run (so loaded or slower machines can be compared).

``--noise`` also reports ESF's sampling noise: the L1 distance between
descriptors of the same scan computed with different seeds, next to the L1
distances between scans.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import time  # noqa: E402
from itertools import combinations  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from lidar_iris_eval.descriptors import get_descriptor  # noqa: E402

TARGETS_MS = {"m2dp": 60.0, "esf": 150.0}
DEFAULT_SCANS = Path(__file__).resolve().parents[2] / "shared/data/kitti/samples/00/velodyne"


def pin_one_core() -> str:
    """Restrict this process to one CPU where the OS allows it; say which."""
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"cpu {cpu}"
    return "not pinned"


def load_scans(folder: Path) -> dict[str, np.ndarray]:
    """KITTI .bin scans of a folder, or one synthetic 120k-point cloud."""
    files = sorted(folder.glob("*.bin")) if folder.is_dir() else []
    if files:
        return {
            f.stem: np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for f in files
        }
    rng = np.random.default_rng(0)
    n = 120_000
    rng_xy = rng.uniform(-60, 60, size=(n, 2))
    z = np.where(rng.random(n) < 0.6, -1.7, rng.uniform(-1.7, 3.0, n))
    return {"synthetic120k": np.c_[rng_xy, z].astype(np.float32)}


def time_calls(fn, repeats: int) -> tuple[list[float], list[float]]:
    """Wall and CPU times (ms) of ``repeats`` calls after one warm-up call.

    CPU time is less disturbed by other processes on a shared machine.
    """
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        cpu.append((time.process_time() - start_cpu) * 1e3)
        wall.append((time.perf_counter() - start) * 1e3)
    return wall, cpu


def calibration_ms(repeats: int) -> float:
    """Median time of a fixed NumPy workload (sorting 1M floats), as a machine yardstick."""
    data = np.random.default_rng(1).random(1_000_000)
    return float(np.median(time_calls(lambda: np.sort(data), repeats)[0]))


def esf_noise(scans: dict[str, np.ndarray], seeds: int = 4) -> dict[str, object]:
    """L1 distances between seeds of the same scan, and between scans (seed 0)."""
    descs = [get_descriptor("esf", seed=s) for s in range(seeds)]
    hists = {k: [d.compute(v) for d in descs] for k, v in scans.items()}
    within = {
        k: [round(descs[0].distance(a, b)[0], 4) for a, b in combinations(h, 2)]
        for k, h in hists.items()
    }
    between = {
        f"{a}|{b}": round(descs[0].distance(hists[a][0], hists[b][0])[0], 4)
        for a, b in combinations(sorted(hists), 2)
    }
    return {"same_scan_other_seed": within, "between_scans_seed0": between}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=15, help="timed runs per scan")
    parser.add_argument("--scans", type=Path, default=DEFAULT_SCANS, help="folder of KITTI .bin")
    parser.add_argument("--noise", action="store_true", help="also report ESF seed noise")
    parser.add_argument("--json", type=Path, help="write the results here as JSON")
    args = parser.parse_args()

    pinned = pin_one_core()
    scans = load_scans(args.scans)
    points = {k: len(v) for k, v in scans.items()}
    calib = calibration_ms(args.repeats)
    print(f"python {platform.python_version()}, numpy {np.__version__}, {pinned}, 1 thread")
    print(f"scans: {points}")
    print(f"calibration (np.sort of 1M float64): {calib:.1f} ms median")

    results: dict[str, object] = {"points": points, "calibration_ms": calib}
    for name in ("m2dp", "esf"):
        compute = get_descriptor(name).compute
        times, cpu = [], []
        for pts in scans.values():
            wall_ms, cpu_ms = time_calls(lambda pts=pts, f=compute: f(pts), args.repeats)
            times += wall_ms
            cpu += cpu_ms
        median = float(np.median(times))
        q1, q3 = np.percentile(times, [25, 75])
        verdict = "meets" if median <= TARGETS_MS[name] else "MISSES"
        print(
            f"{name:5s} median {median:6.1f} ms wall (IQR {q1:.1f}-{q3:.1f}, n={len(times)}), "
            f"{np.median(cpu):.1f} ms CPU, {median / calib:.2f}x calibration; "
            f"target <= {TARGETS_MS[name]:.0f} ms: {verdict}"
        )
        results[name] = {
            "median_ms": median,
            "q1_ms": float(q1),
            "q3_ms": float(q3),
            "median_cpu_ms": float(np.median(cpu)),
            "runs": len(times),
            "ratio_to_calibration": median / calib,
            "target_ms": TARGETS_MS[name],
        }
    if args.noise:
        noise = esf_noise(scans)
        print("ESF L1, same scan, seeds 0-3 pairwise:", noise["same_scan_other_seed"])
        print("ESF L1, between scans, seed 0:", noise["between_scans_seed0"])
        results["esf_noise"] = noise
    if args.json:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
