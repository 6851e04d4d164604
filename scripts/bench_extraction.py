#!/usr/bin/env python
"""Extraction and single-pair time: today's code vs the routes it replaced, same run.

Usage::

    taskset -c 1 python scripts/bench_extraction.py [--scans DIR] [--rounds 7] [--json FILE]
        [--descriptors scan-context,m2dp,esf,bevplace,overlap-transformer]

On a shared machine absolute times move with the load, so each measurement
alternates the current implementation and the previous one (the routes
the current ones replaced, still in the code as their references) round
by round, on the same real KITTI scans (default
``../shared/data/kitti/samples/00/velodyne``) in one process with one
BLAS/numba thread; the ratio previous / current is the speed-up. The
authors' C++ figures (:data:`lidar_iris_eval.bench.extraction.CPP_FIGURES`)
are printed next to the medians as published figures from another machine,
never as a ratio (``liris bench --cpp DIR`` times your own build in the run).

Previous routes: Scan Context's sort-based voxel grid and the batched
``pairwise`` for one pair; M2DP's ``atan2`` route (float64 aligned cloud,
float32 ``arctan2``, compiled binning: the previous release's default); ESF's
``esf_histogram_numpy`` (tracing and histograms), ``trace_lines_numpy``,
``normalise_numpy`` and ``sample_triangles_previous`` (NumPy triplet geometry);
BEVPlace++'s stride-1 convolutions as a product per tap then ``+=`` (today each
tap's GEMM adds into the output itself, ``network._gemm_add``).
OverlapTransformer has no previous route (both columns time today's code: the
ratio shows the noise of the measurement).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from lidar_iris_eval.bench.extraction import (  # noqa: E402
    CPP_FIGURES,
    PUBLISHED_LABEL,
    load_bin_scans,
)
from lidar_iris_eval.descriptors import get_descriptor  # noqa: E402
from lidar_iris_eval.descriptors.bevplace import network as bev_network  # noqa: E402
from lidar_iris_eval.descriptors.esf import descriptor as esf_module  # noqa: E402
from lidar_iris_eval.descriptors.m2dp import descriptor as m2dp_module  # noqa: E402
from lidar_iris_eval.descriptors.scan_context import descriptor as sc_module  # noqa: E402

DEFAULT_SCANS = Path(__file__).resolve().parents[2] / "shared/data/kitti/samples/00/velodyne"


@contextlib.contextmanager
def previous(name: str):
    """Swap the current route of ``name`` for the route it replaced."""
    if name == "scan-context":
        module, attr, old = sc_module.voxel, "voxel_centroids", lambda *a, **k: None
    elif name == "m2dp":  # the atan2 route (route: atan2), which the fast route replaced
        module, attr, old = m2dp_module, "fast_route_applies", lambda params: False
    elif name == "bevplace":  # a temporary product per tap, then +=
        module, attr, old = bev_network, "_gemm_add", _product_then_add
    elif name == "overlap-transformer":  # unchanged: today's code in both columns
        yield
        return
    else:  # NumPy histograms and tracing, NumPy normalisation, NumPy geometry recomputed
        swaps = [(esf_module, "esf_histogram", esf_module.esf_histogram_numpy),
                 (esf_module, "trace_lines", esf_module.trace_lines_numpy),
                 (esf_module, "normalise", esf_module.normalise_numpy),
                 (esf_module, "sample_triangles", esf_module.sample_triangles_previous)]
        with contextlib.ExitStack() as stack:
            for module, attr, old in swaps:
                stack.enter_context(_swapped(module, attr, old))
            yield
        return
    with _swapped(module, attr, old):
        yield


def _product_then_add(out: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    out += a @ b


@contextlib.contextmanager
def _swapped(module, attr, old):
    new = getattr(module, attr)
    setattr(module, attr, old)
    try:
        yield
    finally:
        setattr(module, attr, new)


def timed(fn, count: int = 1) -> float:
    start = time.process_time()
    for _ in range(count):
        fn()
    return (time.process_time() - start) / count


def measure(name: str, scans: list[np.ndarray], rounds: int, pair_calls: int) -> dict:
    """Alternating rounds of the current and the previous route of one descriptor."""
    desc = get_descriptor(name, preset="reference")
    for s in scans:  # warm-up, compile
        desc.compute(s)
        with previous(name):
            desc.compute(s)
    cur, old = [], []
    for _ in range(rounds):
        for s in scans:
            cur.append(timed(lambda s=s: desc.compute(s)))
            with previous(name):
                old.append(timed(lambda s=s: desc.compute(s)))
    row = {"extract_ms": 1e3 * float(np.median(cur)),
           "previous_extract_ms": 1e3 * float(np.median(old))}
    row["extract_speedup"] = row["previous_extract_ms"] / row["extract_ms"]
    row["published_cpp_extract_ms"] = CPP_FIGURES.get(name, {}).get("extract_ms")
    if name == "scan-context":
        a, b = desc.compute(scans[0]), desc.compute(scans[1])
        one, other = a.reshape(1), b.reshape(1)
        pc, po = [], []
        for _ in range(rounds):
            pc.append(timed(lambda: desc.distance(a, b), pair_calls))
            po.append(timed(lambda: desc.pairwise(one, other), max(1, pair_calls // 10)))
        row["pair_us"] = 1e6 * float(np.median(pc))
        row["previous_pair_us"] = 1e6 * float(np.median(po))
        row["pair_speedup"] = row["previous_pair_us"] / row["pair_us"]
        row["published_cpp_pair_us"] = CPP_FIGURES[name]["pair_us"]
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scans", type=Path, default=DEFAULT_SCANS)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--pair-calls", type=int, default=300)
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--descriptors", default="scan-context,m2dp,esf",
                        help="comma-separated subset of scan-context,m2dp,esf,bevplace,"
                        "overlap-transformer")
    args = parser.parse_args()
    pinned = "not pinned"
    if hasattr(os, "sched_getaffinity"):
        cpus = os.sched_getaffinity(0)
        pinned = f"{len(cpus)} cpu(s) allowed" + (" (pinned)" if len(cpus) == 1 else "")
    scans = load_bin_scans(args.scans)
    if not scans:
        raise SystemExit(f"no .bin scans in {args.scans}")
    report = {"scans": len(scans), "points_median": float(np.median([len(s) for s in scans])),
              "cpu": pinned, "load_average_start": list(os.getloadavg()), "rows": {}}
    for name in args.descriptors.split(","):
        report["rows"][name] = measure(name, scans, args.rounds, args.pair_calls)
    report["load_average_end"] = list(os.getloadavg())
    print(f"{report['scans']} scans of ~{report['points_median']:.0f} points, {pinned}, "
          f"load average {report['load_average_start'][0]:.2f} -> "
          f"{report['load_average_end'][0]:.2f} (CPU time, median of alternating rounds)")
    print(f"{'step':<28}{'now':>10}{'previous':>10}{'speed-up':>10}{'C++*':>8}")
    for name, row in report["rows"].items():
        cpp = row["published_cpp_extract_ms"]
        print(f"{name + ' extraction (ms)':<28}{row['extract_ms']:>10.2f}"
              f"{row['previous_extract_ms']:>10.2f}{row['extract_speedup']:>9.2f}x"
              f"{'-' if cpp is None else cpp:>8}")
        if "pair_us" in row:
            print(f"{name + ' one pair (us)':<28}{row['pair_us']:>10.1f}"
                  f"{row['previous_pair_us']:>10.1f}{row['pair_speedup']:>9.2f}x"
                  f"{row['published_cpp_pair_us']:>8}")
    print(f"* C++: {PUBLISHED_LABEL} (not measured here, not a ratio)")
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
