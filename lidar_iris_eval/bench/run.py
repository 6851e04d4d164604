"""The benchmark run: every measurement of every descriptor, as one JSON-ready report."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from lidar_iris_eval import __version__
from lidar_iris_eval.bench.bars import evaluate_bars
from lidar_iris_eval.bench.isolate import (
    MatchingJob,
    run_isolated,
    run_matching,
    save_descriptors,
)
from lidar_iris_eval.bench.measure import (
    extraction_summary,
    kernel_throughput,
    loop_comparison,
    machine_info,
    points_per_scan,
    sample_pairs,
)
from lidar_iris_eval.bench.settings import BenchSettings
from lidar_iris_eval.cache import DescriptorCache
from lidar_iris_eval.config import params_dict
from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.extract import extract


def bench_descriptor(seq, desc: Descriptor, cache: DescriptorCache, positions: np.ndarray,
                     frame: str, settings: BenchSettings, scratch: Path,
                     progress: bool = False,
                     log: Callable[[str], object] | None = None) -> dict[str, Any]:
    """Every measurement of one descriptor on ``seq`` (see the module docstring)."""
    say = log or (lambda _msg: None)
    say(f"{desc.name} ({desc.preset}): extraction")
    start = time.perf_counter()
    db = extract(seq, desc, cache=cache, workers=settings.workers, progress=progress)
    entry: dict[str, Any] = {
        "descriptor": desc.name, "preset": desc.preset, "params": params_dict(desc.params),
        "symmetric": bool(desc.symmetric),
        "extraction": {**extraction_summary(db), "call_s": time.perf_counter() - start,
                       "workers": settings.workers},
    }
    descs = db.descriptors
    say(f"{desc.name}: kernel throughput ({min(settings.kernel_queries, len(descs))} queries "
        f"x {len(descs)} frames)")
    entry["kernel"] = kernel_throughput(desc, descs, settings.kernel_queries,
                                        settings.kernel_repeats)
    if settings.loop_pairs and len(descs) > 1:
        rng = np.random.default_rng(settings.seed)
        pairs = sample_pairs(len(descs), settings.loop_pairs, settings.loop_pool, rng)
        say(f"{desc.name}: per-pair loops on {len(pairs)} random pairs")
        entry["loop"] = loop_comparison(desc, descs, pairs, entry["kernel"])
    scratch.mkdir(parents=True, exist_ok=True)
    path = Path(save_descriptors(scratch / f"{desc.name}-{os.getpid()}", descs))
    del db, descs
    try:
        for protocol in settings.protocols:
            say(f"{desc.name}: protocol {protocol}"
                + (" in a fresh process" if settings.isolate else ""))
            job = MatchingJob(desc, str(path), positions, frame, protocol, settings.exclude,
                              settings.radius, settings.pair_budget, progress)
            result = run_isolated(job) if settings.isolate else run_matching(job)
            result["isolated"] = settings.isolate
            entry[f"protocol{protocol}"] = result
    finally:
        path.unlink(missing_ok=True)
    return entry


def run_benchmark(seq, descriptors: list[Descriptor], work_dir: str | os.PathLike,
                  settings: BenchSettings | None = None, progress: bool = False,
                  log: Callable[[str], object] | None = None,
                  pose_frame: str = "camera") -> dict[str, Any]:
    """Benchmark ``descriptors`` on ``seq``; returns the JSON-ready report.

    Descriptors are cached under ``work_dir/cache``, so a rerun skips
    extraction (its per-scan times are those of the run that computed them).
    """
    settings = settings or BenchSettings()
    work_dir = Path(work_dir)
    started = time.time()
    load_start = os.getloadavg()
    frame = seq.resolve_pose_frame(pose_frame)
    positions = seq.positions(frame)
    cache = DescriptorCache(work_dir / "cache")
    entries = [
        bench_descriptor(seq, d, cache, positions, frame, settings, work_dir / "scratch",
                         progress, log)
        for d in descriptors
    ]
    report = {
        "liris_version": __version__,
        "started_unix": started,
        "total_s": time.time() - started,
        "machine": machine_info(),
        "load_average": {"start": list(load_start), "end": list(os.getloadavg())},
        "sequence": {"name": seq.name, "path": str(seq.path), "frames": len(seq),
                     "pose_frame": frame, **points_per_scan(seq)},
        "settings": dataclasses.asdict(settings),
        "descriptors": entries,
    }
    report["bars"] = evaluate_bars(report)
    return report
