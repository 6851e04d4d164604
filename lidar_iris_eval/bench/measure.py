"""Measurements of one descriptor: extraction statistics, kernel throughput, loops."""

from __future__ import annotations

import os
import platform
import time
from typing import Any

import numpy as np

from lidar_iris_eval import __version__
from lidar_iris_eval.bench.references import reference_loop
from lidar_iris_eval.descriptors.base import Descriptor


def sample_pairs(n: int, count: int, pool: int, rng: np.random.Generator) -> np.ndarray:
    """``(K, 2)`` distinct ordered pairs ``i != j`` among ``min(pool, n)`` random frames.

    ``K = min(count, p * (p - 1))`` for a pool of ``p`` frames.
    """
    frames = rng.choice(n, size=min(pool, n), replace=False)
    p = len(frames)
    total = p * (p - 1)
    flat = rng.choice(total, size=min(count, total), replace=False)
    i, j = np.divmod(flat, p - 1) if p > 1 else (flat, flat)
    j = j + (j >= i)  # skip the diagonal
    return np.stack([frames[i], frames[j]], axis=1)


def _nbytes(descs) -> int:
    """Bytes of a stack of descriptors or of feature sets (their flat arrays)."""
    if hasattr(descs, "nbytes"):
        return int(descs.nbytes)
    return int(sum(np.asarray(v).nbytes for v in descs.to_arrays().values()))


def extraction_summary(db) -> dict[str, Any]:
    """Per-scan ``compute`` time statistics in milliseconds."""
    ms = np.asarray(db.extract_s, dtype=np.float64) * 1e3
    p10, q1, med, q3, p90 = np.percentile(ms, [10, 25, 50, 75, 90])
    return {
        "scans": len(ms), "median_ms": med, "q1_ms": q1, "q3_ms": q3, "p10_ms": p10,
        "p90_ms": p90, "mean_ms": float(ms.mean()), "max_ms": float(ms.max()),
        "read_median_ms": float(np.median(db.read_s) * 1e3), "from_cache": db.from_cache,
        "descriptor_bytes": int(_nbytes(db.descriptors) // max(1, len(db))),
    }


def kernel_throughput(desc: Descriptor, descs: np.ndarray, queries: int,
                      repeats: int) -> dict[str, Any]:
    """Pairs per second of one ``pairwise`` call: a block of queries vs the whole database.

    One small call first loads compiled code, so that is not timed.
    """
    desc.pairwise(descs[:2], descs[:2])
    block = descs[: min(queries, len(descs))]
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        desc.pairwise(block, descs)
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    pairs = len(block) * len(descs)
    wall, cpu = float(np.median(walls)), float(np.median(cpus))
    return {
        "queries": len(block), "database": len(descs), "pairs": pairs, "repeats": repeats,
        "wall_s": wall, "cpu_s": cpu, "pairs_per_s": pairs / wall,
        "us_per_pair": 1e6 * wall / pairs, "cpu_us_per_pair": 1e6 * cpu / pairs,
    }


def loop_comparison(desc: Descriptor, descs: np.ndarray, pairs: np.ndarray,
                    kernel: dict[str, Any]) -> dict[str, Any]:
    """Batched vs single-pair vs reference loop on ``pairs``.

    * ``batched_equals_single``: ``pairwise`` over the frames involved, read at
      the pairs, is ``np.array_equal`` to ``distance`` called pair by pair
      (distances; yaws separately, NaN equal to NaN).
    * the reference loop's distances, their largest difference from the batched
      ones and whether they are identical, and the loop's per-pair time with
      its ratio to the kernel's (wall and CPU).
    """
    rows, cols = np.unique(pairs[:, 0]), np.unique(pairs[:, 1])
    d_blk, y_blk = desc.pairwise(descs[rows], descs[cols])
    at = (np.searchsorted(rows, pairs[:, 0]), np.searchsorted(cols, pairs[:, 1]))
    batched_d, batched_y = np.asarray(d_blk)[at], np.asarray(y_blk)[at]
    wall = time.perf_counter()
    single = np.array([desc.distance(descs[i], descs[j]) for i, j in pairs], dtype=np.float64)
    single_s = time.perf_counter() - wall
    out: dict[str, Any] = {
        "pairs": len(pairs),
        "batched_equals_single": bool(np.array_equal(batched_d, single[:, 0], equal_nan=True)),
        "batched_yaw_equals_single": bool(np.array_equal(batched_y, single[:, 1],
                                                         equal_nan=True)),
        "single_distance_us_per_pair": 1e6 * single_s / max(1, len(pairs)),
    }
    ref = reference_loop(desc, descs, pairs)
    if ref is None:
        out["reference"] = None
        return out
    ref_d, ref_wall, ref_cpu = ref
    both = ~np.isnan(ref_d) & ~np.isnan(batched_d)
    per_pair, per_pair_cpu = ref_wall / len(pairs), ref_cpu / len(pairs)
    out["reference"] = {
        "identical": bool(np.array_equal(ref_d, batched_d, equal_nan=True)),
        "max_abs_diff": float(np.max(np.abs(ref_d[both] - batched_d[both]))) if both.any()
        else 0.0,
        "nan_mismatches": int(np.count_nonzero(np.isnan(ref_d) != np.isnan(batched_d))),
        "us_per_pair": 1e6 * per_pair,
        "cpu_us_per_pair": 1e6 * per_pair_cpu,
        "speedup": per_pair / (kernel["wall_s"] / kernel["pairs"]),
        "speedup_cpu": per_pair_cpu / (kernel["cpu_s"] / kernel["pairs"]),
    }
    return out


def points_per_scan(seq, samples: int = 20) -> dict[str, Any]:
    """Median point count of ``samples`` evenly spaced scans: extraction time
    scales with it (a real KITTI HDL-64E scan has about 120k points)."""
    frames = np.unique(np.linspace(0, len(seq) - 1, min(samples, len(seq))).astype(int))
    counts = [len(seq[int(i)]) for i in frames]
    return {"points_per_scan_median": float(np.median(counts)), "points_sampled_scans": len(frames)}


def machine_info() -> dict[str, Any]:
    """What ran the benchmark: CPU, counts and library versions."""
    import numba

    return {
        "platform": platform.platform(), "processor": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "usable_cpus": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "python": platform.python_version(), "numpy": np.__version__,
        "numba": numba.__version__, "numba_threads": numba.get_num_threads(),
        "liris": __version__,
    }
