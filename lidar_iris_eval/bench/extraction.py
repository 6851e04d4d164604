"""Extraction per full-resolution scan and single-pair time, next to the authors' C++.

The protocol passes of a benchmark run on a sequence whose resolution may be
reduced; the per-scan figures that compare with the original implementations
need full-resolution scans (about 120k points, like a KITTI HDL-64E scan) and
one core. :func:`measure_against_cpp` runs ``compute`` on each scan and the
single-pair ``distance`` on pairs of them, in a spawned child pinned to one
CPU with one BLAS/numba thread, and reports medians with their ratio to the
published C++ timings (:data:`CPP_FIGURES`; ratio < 1 means faster than C++).
"""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor

#: one-thread timings of the original implementations on real KITTI scans
#: (issue 18's table; LiDAR Iris from ALGORITHMS.md: image 2.6 ms + features
#: 2.8 ms, compare 3.0 ms with matchNum 0). None: no C++ exists (M2DP's
#: reference is MATLAB/Octave, 276 ms per scan) or no figure was published.
CPP_FIGURES: dict[str, dict[str, Any]] = {
    "lidar-iris": {"extract_ms": 5.4, "pair_us": 3000.0,
                   "source": "authors' C++ (LiDAR-Iris), one thread"},
    "scan-context": {"extract_ms": 3.5, "pair_us": 31.0,
                     "source": "authors' C++ (scancontext) + PCL VoxelGrid, one thread"},
    "esf": {"extract_ms": 33.0, "pair_us": None, "source": "PCL 1.13 ESFEstimation"},
    "m2dp": {"extract_ms": None, "pair_us": None,
             "source": "no C++ (authors' MATLAB: 276 ms per scan under Octave)"},
}
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS")


def load_bin_scans(folder: str | os.PathLike, limit: int = 8) -> list[np.ndarray]:
    """Up to ``limit`` KITTI ``.bin`` scans of ``folder`` as ``(N, 3)`` float32 arrays."""
    files = sorted(Path(folder).glob("*.bin"))[:limit]
    return [np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for f in files]


def _median_ms(fn, repeats: int) -> float:
    fn()  # warm-up: compiled kernels, caches
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def _pin_one_core() -> tuple[str, set[int] | None]:
    """Pin this process to one CPU; returns a label and the CPUs to restore afterwards."""
    if hasattr(os, "sched_setaffinity"):
        before = os.sched_getaffinity(0)
        cpu = max(before)
        os.sched_setaffinity(0, {cpu})
        return f"cpu {cpu}", before
    return "not pinned", None


def measure_here(descriptors: list[Descriptor], scans: list[np.ndarray], repeats: int = 5,
                 pair_repeats: int = 200) -> dict[str, Any]:
    """Per-scan extraction and single-pair times of each descriptor, in this process."""
    pinned, before = _pin_one_core()
    out: dict[str, Any] = {"pinned": pinned, "scans": len(scans),
                           "points_median": float(np.median([len(s) for s in scans])),
                           "descriptors": {}}
    try:
        for desc in descriptors:
            out["descriptors"][f"{desc.name}:{desc.preset}"] = _measure_one(
                desc, scans, repeats, pair_repeats)
    finally:
        if before is not None:
            os.sched_setaffinity(0, before)
    return out


def _measure_one(desc: Descriptor, scans: list[np.ndarray], repeats: int,
                 pair_repeats: int) -> dict[str, Any]:
    per_scan = [_median_ms(lambda s=s: desc.compute(s), repeats) for s in scans]
    descs = [desc.compute(s) for s in scans]
    pairs = [(a, b) for a in range(len(descs)) for b in range(len(descs)) if a != b]
    pair_us = None
    if pairs:
        def one_round():
            for a, b in pairs:
                desc.distance(descs[a], descs[b])

        rounds = max(1, pair_repeats // len(pairs))
        pair_us = 1e3 * _median_ms(one_round, rounds) / len(pairs)
    return {"descriptor": desc.name, "preset": desc.preset,
            "extract_ms": float(np.median(per_scan)), "extract_ms_per_scan": per_scan,
            "pair_us": pair_us}


def _child(descriptors, scans, repeats, pair_repeats):
    return measure_here(descriptors, scans, repeats, pair_repeats)


def _init_child() -> None:
    for var in _THREAD_VARS:
        os.environ[var] = "1"


def measure_against_cpp(descriptors: list[Descriptor], scans: list[np.ndarray],
                        repeats: int = 5, pair_repeats: int = 200,
                        isolate: bool = True) -> dict[str, Any]:
    """Medians per descriptor with the C++ figures and the ratios ours / C++.

    ``isolate`` runs the timing in a spawned child with one thread per
    library, pinned to one CPU (environment variables are read when NumPy
    and numba load, hence a fresh process).
    """
    if isolate:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=1, mp_context=context,
                                 initializer=_init_child) as pool:
            result = pool.submit(_child, descriptors, scans, repeats, pair_repeats).result()
    else:
        result = measure_here(descriptors, scans, repeats, pair_repeats)
    result["load_average"] = list(os.getloadavg())
    for entry in result["descriptors"].values():
        cpp = CPP_FIGURES.get(entry["descriptor"], {})
        entry["cpp_extract_ms"] = cpp.get("extract_ms")
        entry["cpp_pair_us"] = cpp.get("pair_us")
        entry["cpp_source"] = cpp.get("source")
        entry["extract_ratio_to_cpp"] = _ratio(entry["extract_ms"], entry["cpp_extract_ms"])
        entry["pair_ratio_to_cpp"] = _ratio(entry["pair_us"], entry["cpp_pair_us"])
    return result


def _ratio(ours: float | None, theirs: float | None) -> float | None:
    return None if ours is None or not theirs else ours / theirs


def cpp_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    """Table rows: ours, C++ and the ratio for extraction and single-pair time."""
    def fmt(v, spec):
        return "-" if v is None else format(v, spec)

    rows = []
    for key, e in result["descriptors"].items():
        rows.append({
            "descriptor": key,
            "extract_ms": fmt(e["extract_ms"], ".2f"),
            "C++_ms": fmt(e["cpp_extract_ms"], ".1f"),
            "extract_x_C++": fmt(e["extract_ratio_to_cpp"], ".2f"),
            "pair_us": fmt(e["pair_us"], ".1f"),
            "C++_us": fmt(e["cpp_pair_us"], ".0f"),
            "pair_x_C++": fmt(e["pair_ratio_to_cpp"], ".2f"),
        })
    return rows
