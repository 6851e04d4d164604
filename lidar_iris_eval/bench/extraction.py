"""Extraction per full-resolution scan and single-pair time, next to the authors' C++.

The protocol passes of a benchmark run on a sequence whose resolution may be
reduced; the per-scan figures that compare with the original implementations
need full-resolution scans (about 120k points, like a KITTI HDL-64E scan) and
one core. :func:`measure_extraction` runs ``compute`` on each scan and the
single-pair ``distance`` on pairs of them, in a spawned child pinned to one
CPU with one BLAS/numba thread, and reports medians of CPU time.

A ratio to C++ is computed only from C++ timed in the same run: with
``drivers`` (``liris bench --cpp DIR``, :mod:`.drivers`), each round times
our code and then the user-built reference driver on the same scans, on the
same CPU. Without them, the remembered figures of :data:`CPP_FIGURES` are
attached as ``published_*`` values, labelled "published figures, another
machine", and no ratio is formed.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from lidar_iris_eval.bench.drivers import run_driver
from lidar_iris_eval.descriptors.base import Descriptor

#: one-thread timings of the original implementations on real KITTI scans, as
#: published for another machine (issue 18's table; LiDAR Iris from
#: ALGORITHMS.md: image 2.6 ms + features 2.8 ms, compare 3.0 ms with matchNum
#: 0). For orientation only: never divided into a ratio (that needs both sides
#: timed in one run: ``liris bench --cpp DIR``). None: no C++ exists (M2DP's
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
#: how remembered figures are labelled wherever they are shown
PUBLISHED_LABEL = "published figures, another machine"
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                "NUMBA_NUM_THREADS")


def bin_files(folder: str | os.PathLike, limit: int = 8) -> list[Path]:
    """Up to ``limit`` KITTI ``.bin`` files of ``folder``, sorted."""
    return sorted(Path(folder).glob("*.bin"))[:limit]


def load_bin_scans(folder: str | os.PathLike, limit: int = 8) -> list[np.ndarray]:
    """Up to ``limit`` KITTI ``.bin`` scans of ``folder`` as ``(N, 3)`` float32 arrays."""
    return [read_bin(f) for f in bin_files(folder, limit)]


def read_bin(path: str | os.PathLike) -> np.ndarray:
    """One KITTI ``.bin`` scan as ``(N, 3)`` float32."""
    return np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3].copy()


def _cpu_ms(fn) -> float:
    start = time.process_time()
    fn()
    return 1e3 * (time.process_time() - start)


def _pin_one_core() -> tuple[str, set[int] | None]:
    """Pin this process to one CPU; returns a label and the CPUs to restore afterwards."""
    if hasattr(os, "sched_setaffinity"):
        before = os.sched_getaffinity(0)
        cpu = max(before)
        os.sched_setaffinity(0, {cpu})
        return f"cpu {cpu}", before
    return "not pinned", None


def measure_here(descriptors: list[Descriptor], scans: list[np.ndarray], rounds: int = 5,
                 pair_repeats: int = 200, drivers: dict[str, Path] | None = None,
                 scan_paths: list[str] | None = None) -> dict[str, Any]:
    """Per-scan extraction and single-pair CPU times of each descriptor, in this process.

    ``rounds`` alternate our code and, when ``drivers`` has one for the
    descriptor, the driver on ``scan_paths`` (the same scans as files);
    per-scan figures are medians over rounds.
    """
    drivers = drivers or {}
    pinned, before = _pin_one_core()
    out: dict[str, Any] = {"pinned": pinned, "scans": len(scans), "rounds": rounds,
                           "points_median": float(np.median([len(s) for s in scans])),
                           "descriptors": {}}
    try:
        for desc in descriptors:
            out["descriptors"][f"{desc.name}:{desc.preset}"] = _measure_one(
                desc, scans, rounds, pair_repeats, drivers.get(desc.name), scan_paths)
    finally:
        if before is not None:
            os.sched_setaffinity(0, before)
    return out


def _measure_one(desc: Descriptor, scans: list[np.ndarray], rounds: int, pair_repeats: int,
                 driver: Path | None, scan_paths: list[str] | None) -> dict[str, Any]:
    descs = [desc.compute(s) for s in scans]  # warm-up: compiled kernels, caches
    pairs = [(a, b) for a in range(len(descs)) for b in range(len(descs)) if a != b]
    per_round = max(1, pair_repeats // max(1, len(pairs) * rounds))
    ours = np.empty((rounds, len(scans)))
    ours_pair, theirs, theirs_pair, theirs_wall = [], [], [], []
    for r in range(rounds):
        for i, s in enumerate(scans):
            ours[r, i] = _cpu_ms(lambda s=s: desc.compute(s))
        if pairs:
            def one_round():
                for _ in range(per_round):
                    for a, b in pairs:
                        desc.distance(descs[a], descs[b])

            ours_pair.append(1e3 * _cpu_ms(one_round) / (per_round * len(pairs)))
        if driver is not None:
            start = time.perf_counter()
            got = run_driver(driver, scan_paths)
            theirs_wall.append(time.perf_counter() - start)
            theirs.append(got["extract_ms"])
            if got["pair_us"]:
                theirs_pair.append(float(np.median(got["pair_us"])))
    per_scan = np.median(ours, axis=0)
    entry: dict[str, Any] = {
        "descriptor": desc.name, "preset": desc.preset, "clock": "process CPU time",
        "extract_ms": float(np.median(per_scan)), "extract_ms_per_scan": per_scan.tolist(),
        "pair_us": float(np.median(ours_pair)) if ours_pair else None,
    }
    published = CPP_FIGURES.get(desc.name, {})
    entry["published"] = {"label": PUBLISHED_LABEL, "extract_ms": published.get("extract_ms"),
                          "pair_us": published.get("pair_us"),
                          "source": published.get("source")}
    if driver is None:
        entry["cpp"] = None
        return entry
    cpp_scan = np.median(np.asarray(theirs), axis=0)
    cpp_pair = float(np.median(theirs_pair)) if theirs_pair else None
    entry["cpp"] = {
        "driver": str(driver), "measured": "in this run, same scans, same CPU, interleaved",
        "extract_ms": float(np.median(cpp_scan)), "extract_ms_per_scan": cpp_scan.tolist(),
        "pair_us": cpp_pair, "driver_wall_s_per_round": theirs_wall,
        # per scan ours / theirs, then the median over scans (< 1: ours faster)
        "extract_ratio": _median_ratio(per_scan, cpp_scan),
        "pair_ratio": _ratio(entry["pair_us"], cpp_pair),
    }
    return entry


def _median_ratio(ours: np.ndarray, theirs: np.ndarray) -> float | None:
    ok = theirs > 0
    return float(np.median(ours[ok] / theirs[ok])) if ok.any() else None


def _child(descriptors, scans, rounds, pair_repeats, drivers, scan_paths):
    return measure_here(descriptors, scans, rounds, pair_repeats, drivers, scan_paths)


def _init_child() -> None:
    for var in _THREAD_VARS:
        os.environ[var] = "1"


def measure_extraction(descriptors: list[Descriptor], scans: list[np.ndarray],
                       rounds: int = 5, pair_repeats: int = 200, isolate: bool = True,
                       drivers: dict[str, Path] | None = None,
                       scan_paths: list[str] | None = None) -> dict[str, Any]:
    """Medians per descriptor; C++ ratios only for the ``drivers`` timed in this run.

    ``isolate`` runs the timing in a spawned child with one thread per
    library, pinned to one CPU (environment variables are read when NumPy
    and numba load, hence a fresh process). ``scan_paths`` are the ``.bin``
    files of ``scans``, needed with ``drivers``.
    """
    if drivers and (scan_paths is None or len(scan_paths) != len(scans)):
        raise ValueError("drivers need the scans' .bin paths (scan_paths)")
    args = (descriptors, scans, rounds, pair_repeats, drivers, scan_paths)
    load_start = list(os.getloadavg())
    if isolate:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=1, mp_context=context,
                                 initializer=_init_child) as pool:
            result = pool.submit(_child, *args).result()
    else:
        result = measure_here(*args)
    result["load_average"] = {"start": load_start, "end": list(os.getloadavg())}
    return result


def _ratio(ours: float | None, theirs: float | None) -> float | None:
    return None if ours is None or not theirs else ours / theirs


def cpp_rows(result: dict[str, Any]) -> list[dict[str, Any]]:
    """Table rows. With a measured driver: ours, C++ and the ratio; without one:
    ours next to the published figures (another machine), and no ratio column."""
    def fmt(v, spec):
        return "-" if v is None else format(v, spec)

    measured = any(e.get("cpp") for e in result["descriptors"].values())
    rows = []
    for key, e in result["descriptors"].items():
        row = {"descriptor": key, "extract_ms": fmt(e["extract_ms"], ".2f")}
        cpp = e.get("cpp")
        if measured:
            row.update({
                "C++_ms": fmt(cpp and cpp["extract_ms"], ".2f"),
                "extract_x_C++": fmt(cpp and cpp["extract_ratio"], ".2f"),
                "pair_us": fmt(e["pair_us"], ".1f"),
                "C++_us": fmt(cpp and cpp["pair_us"], ".1f"),
                "pair_x_C++": fmt(cpp and cpp["pair_ratio"], ".2f"),
            })
        else:
            pub = e["published"]
            row.update({
                "published_C++_ms": fmt(pub["extract_ms"], ".1f"),
                "pair_us": fmt(e["pair_us"], ".1f"),
                "published_C++_us": fmt(pub["pair_us"], ".0f"),
            })
        rows.append(row)
    return rows


def cpp_heading(result: dict[str, Any]) -> str:
    """The line above the table: what the C++ columns are."""
    scans = f"{result['scans']} scans of {result['points_median']:.0f} points"
    source = result.get("scan_source")
    scans += f", {source}" if source else ""
    if any(e.get("cpp") for e in result["descriptors"].values()):
        return (f"per full-resolution scan on one core ({scans}, {result['rounds']} "
                "interleaved rounds, CPU time); C++ timed in this run by the --cpp drivers, "
                "ratio ours / C++ (< 1: faster):")
    return (f"per full-resolution scan on one core ({scans}, CPU time); C++ columns are "
            f"{PUBLISHED_LABEL} (not a ratio; time your own build with --cpp DIR):")
