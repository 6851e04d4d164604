#!/usr/bin/env python
"""Scan Context benchmarks: extraction, batched kernel vs a per-pair loop, protocol 2.

Usage::

    python scripts/bench_scan_context.py [--frames 4541] [--block 512]
        [--presets exhaustive,reference] [--repeats 15] [--loop-pairs 200]
        [--skip-protocol2] [--json FILE]

Three measurements, each printed as medians:

1. **Extraction** (one core, one BLAS thread, in a pinned child process):
   ``ScanContext.compute`` on the real ~120k-point KITTI scans in
   ``../shared/data/kitti/samples/00/velodyne`` (a synthetic 120k-point cloud
   if absent), plus the voxel grid alone. Target: <= 15 ms per scan.
2. **Kernel vs per-pair loop** (same child, one core): pairs per second of
   ``pairwise`` on a block of queries against a database, and of a
   straightforward per-pair NumPy loop that follows the authors' C++ (roll the
   candidate for each shift, column cosines over columns valid in both), with
   their ratio and the largest distance difference between the two; and the
   cost of one query against a ``--frames`` database with ``distances`` (which
   prepares the database each call) and with a reused ``matcher``.
3. **Protocol 2** (this process, all cores): every ordered pair of a
   ``--frames`` database, as the evaluation driver does it (blocks of
   ``--block`` queries against the whole database, results kept in two
   ``frames x frames`` float64 arrays), with wall time and peak RSS.
   The descriptors are *perturbed copies of the real scans*: 64 scans made by
   turning, shifting and thinning the real clouds, then replicated to
   ``--frames`` with random column rolls, +-5 % height noise and 3 % of bins
   emptied. Target for ``exhaustive``: <= 120 s for 4541 frames on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

DEFAULT_SCANS = Path(__file__).resolve().parents[2] / "shared/data/kitti/samples/00/velodyne"
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")


# ------------------------------------------------------------------------- helpers
def load_scans(folder: Path):
    """Real KITTI scans of ``folder`` as (N, 3) float32, or one synthetic 120k cloud."""
    import numpy as np

    files = sorted(folder.glob("*.bin")) if folder.is_dir() else []
    if files:
        return {
            f.stem: np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for f in files
        }
    rng = np.random.default_rng(0)
    r = rng.uniform(2, 80, 120_000)
    t = rng.uniform(0, 2 * np.pi, 120_000)
    z = rng.uniform(-2, 3, 120_000)
    return {"synthetic": np.stack([r * np.cos(t), r * np.sin(t), z], 1).astype(np.float32)}


def median_ms(fn, repeats: int) -> float:
    """Median wall time of ``fn()`` in milliseconds after one warm-up call."""
    import numpy as np

    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def loop_distance(q, c, search: str, radius: int) -> float:
    """The straightforward per-pair algorithm (authors' C++), in plain NumPy float64."""
    import numpy as np

    q = q.astype(np.float64)
    c = c.astype(np.float64)
    n = q.shape[1]
    if search == "exhaustive":
        shifts = range(n)
    else:
        vq, vc = q.mean(axis=0), c.mean(axis=0)
        diffs = [np.linalg.norm(vq - np.roll(vc, s)) for s in range(n)]
        start = int(np.argmin(diffs))
        shifts = sorted({(start + j) % n for j in range(-radius, radius + 1)})
    best = np.inf
    norm_q = np.linalg.norm(q, axis=0)
    for s in shifts:
        cs = np.roll(c, s, axis=1)
        norm_c = np.linalg.norm(cs, axis=0)
        valid = (norm_q > 0) & (norm_c > 0)
        if valid.any():
            cos = (q * cs).sum(axis=0)[valid] / (norm_q * norm_c)[valid]
            best = min(best, 1.0 - cos.mean())
    return best


def perturbed_database(desc, scans, frames: int, seed: int = 0):
    """``frames`` descriptors derived from perturbed copies of the real scans."""
    import numpy as np

    rng = np.random.default_rng(seed)
    clouds = list(scans.values())
    base = []
    for _ in range(64):
        p = clouds[rng.integers(len(clouds))].astype(np.float64)
        p = p[rng.random(len(p)) > 0.1]
        t = rng.uniform(0, 2 * np.pi)
        c, s = np.cos(t), np.sin(t)
        xy = p[:, :2] @ np.array([[c, s], [-s, c]]) + rng.uniform(-2, 2, 2)
        pts = np.column_stack([xy, p[:, 2]]) + rng.normal(0, 0.02, (len(p), 3))
        base.append(desc.compute(pts.astype(np.float32)))
    base = np.stack(base)
    sc = base["sc"][rng.integers(0, len(base), frames)].astype(np.float64)
    shifts = rng.integers(0, sc.shape[2], frames)
    cols = (np.arange(sc.shape[2])[None, :] - shifts[:, None]) % sc.shape[2]
    sc = np.take_along_axis(sc, cols[:, None, :], axis=2)
    sc *= rng.uniform(0.95, 1.05, sc.shape)
    sc[rng.random(sc.shape) < 0.03] = 0.0
    db = np.zeros(frames, dtype=desc.dtype)
    db["sc"] = sc.astype(np.float32)
    key = sc.astype(np.float32).astype(np.float64)
    db["ring_key"] = (key != 0).mean(-1) if desc.params.ring_key == "occupancy" else key.mean(-1)
    db["sector_key"] = key.mean(-2)
    return db


# --------------------------------------------------------------- one-core phase
def one_core_phase(args) -> dict:
    """Extraction and kernel-vs-loop figures; runs pinned to one CPU."""
    import numpy as np

    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.descriptors.scan_context import voxel_downsample

    pinned = "not pinned"
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        pinned = f"cpu {cpu}"
    scans = load_scans(Path(args.scans))
    desc = get_descriptor("scan-context", "reference")
    per_scan = {
        name: {
            "points": len(p),
            "compute_ms": median_ms(lambda p=p: desc.compute(p), args.repeats),
            "voxel_grid_ms": median_ms(lambda p=p: voxel_downsample(p, 0.5), args.repeats),
        }
        for name, p in scans.items()
    }
    out = {
        "pinned": pinned,
        "extraction": per_scan,
        "extraction_median_ms": float(np.median([v["compute_ms"] for v in per_scan.values()])),
        "kernel_vs_loop": {},
    }
    db = perturbed_database(desc, scans, 2048, seed=1)
    rng = np.random.default_rng(2)
    for preset in args.presets:
        d = get_descriptor("scan-context", preset)
        queries = db[:64]
        t0 = time.perf_counter()
        dist, _ = d.pairwise(queries, db)
        kernel_s = time.perf_counter() - t0
        qi = rng.integers(0, len(queries), args.loop_pairs)
        mi = rng.integers(0, len(db), args.loop_pairs)
        search = "exhaustive" if d.params.search == "exhaustive" else "sector-key"
        t0 = time.perf_counter()
        loop = [
            loop_distance(queries["sc"][i], db["sc"][j], search, d.params.search_radius)
            for i, j in zip(qi, mi, strict=True)
        ]
        loop_s = time.perf_counter() - t0
        kernel_rate = dist.size / kernel_s
        loop_rate = args.loop_pairs / loop_s
        out["kernel_vs_loop"][preset] = {
            "kernel_pairs_per_s": kernel_rate,
            "loop_pairs_per_s": loop_rate,
            "ratio": kernel_rate / loop_rate,
            "max_abs_diff": float(np.max(np.abs(dist[qi, mi] - np.array(loop)))),
            "kernel_pairs": int(dist.size),
            "loop_pairs": args.loop_pairs,
        }
    big = perturbed_database(desc, scans, args.frames, seed=4)
    out["one_query"] = {}
    for preset in args.presets:
        d = get_descriptor("scan-context", preset)
        matcher = d.matcher(big)
        queries = iter(range(10**9))
        out["one_query"][preset] = {
            "database": len(big),
            "distances_ms": median_ms(lambda d=d, q=queries: d.distances(big[next(q)], big), 10),
            "matcher_ms": median_ms(lambda m=matcher, q=queries: m.distances(big[next(q)]), 10),
            "prepare_ms": median_ms(lambda d=d: d.matcher(big), 10),
        }
    return out


# ----------------------------------------------------------------- protocol 2
def protocol2_phase(args) -> dict:
    """All ordered pairs of a ``--frames`` database, block by block, on all cores."""
    import numpy as np

    from lidar_iris_eval.descriptors import get_descriptor

    scans = load_scans(Path(args.scans))
    out = {}
    for preset in args.presets:
        desc = get_descriptor("scan-context", preset)
        db = perturbed_database(desc, scans, args.frames, seed=3)
        rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        dist = np.empty((len(db), len(db)))
        yaw = np.empty((len(db), len(db)))
        dist.fill(0.0)
        yaw.fill(0.0)
        t0 = time.perf_counter()
        for q0 in range(0, len(db), args.block):
            q1 = min(len(db), q0 + args.block)
            dist[q0:q1], yaw[q0:q1] = desc.pairwise(db[q0:q1], db)
        wall = time.perf_counter() - t0
        rss_after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        out[preset] = {
            "frames": len(db),
            "ordered_pairs": len(db) ** 2,
            "block": args.block,
            "wall_s": wall,
            "pairs_per_s": len(db) ** 2 / wall,
            "peak_rss_mb": rss_after / 1024,
            "rss_mb_before_run": rss_before / 1024,
            "output_arrays_mb": (dist.nbytes + yaw.nbytes) / 2**20,
            "nan_pairs": int(np.isnan(dist).sum()),
            "diag_max": float(np.nanmax(np.diag(dist))),
        }
        del dist, yaw
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, default=4541)
    parser.add_argument("--block", type=int, default=512, help="queries per pairwise call")
    parser.add_argument("--presets", default="exhaustive,reference")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--loop-pairs", type=int, default=200)
    parser.add_argument("--scans", default=str(DEFAULT_SCANS))
    parser.add_argument("--skip-protocol2", action="store_true")
    parser.add_argument("--json", help="also write the results here")
    parser.add_argument("--phase", choices=["one-core"], help=argparse.SUPPRESS)
    args = parser.parse_args()
    args.presets = [p for p in args.presets.split(",") if p]

    if args.phase == "one-core":
        print(json.dumps(one_core_phase(args)))
        return

    env = dict(os.environ, **{v: "1" for v in THREAD_VARS})
    child = subprocess.run(
        [sys.executable, __file__, "--phase", "one-core", *sys.argv[1:]],
        env=env,
        check=True,
        capture_output=True,
        text=True,
    )
    report = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "load_average_start": os.getloadavg(),
        "one_core": json.loads(child.stdout.strip().splitlines()[-1]),
    }
    one = report["one_core"]
    print(f"load average at start: {report['load_average_start']}")
    print(f"extraction ({one['pinned']}, 1 thread):")
    for name, v in one["extraction"].items():
        print(
            f"  {name}: {v['points']} points, compute {v['compute_ms']:.2f} ms "
            f"(voxel grid {v['voxel_grid_ms']:.2f} ms)"
        )
    print(f"  median compute per scan: {one['extraction_median_ms']:.2f} ms (target 15 ms)")
    for preset, v in one["kernel_vs_loop"].items():
        print(
            f"kernel vs per-pair loop [{preset}], 1 core: {v['kernel_pairs_per_s']:.3g} vs "
            f"{v['loop_pairs_per_s']:.3g} pairs/s = x{v['ratio']:.0f}; "
            f"max |d diff| {v['max_abs_diff']:.2e}"
        )
    for preset, v in one["one_query"].items():
        print(
            f"one query vs {v['database']} frames [{preset}], 1 core: distances() "
            f"{v['distances_ms']:.1f} ms, reused matcher {v['matcher_ms']:.1f} ms "
            f"(preparing the database: {v['prepare_ms']:.1f} ms)"
        )
    if not args.skip_protocol2:
        report["protocol2"] = protocol2_phase(args)
        for preset, v in report["protocol2"].items():
            print(
                f"protocol 2 [{preset}], {v['frames']} frames = {v['ordered_pairs']} ordered "
                f"pairs, blocks of {v['block']}: {v['wall_s']:.1f} s ({v['pairs_per_s']:.3g} "
                f"pairs/s), peak RSS {v['peak_rss_mb']:.0f} MB (of which outputs "
                f"{v['output_arrays_mb']:.0f} MB; {v['rss_mb_before_run']:.0f} MB before)"
            )
    report["load_average_end"] = os.getloadavg()
    print(f"load average at end: {report['load_average_end']}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
