"""One protocol pass measured in a freshly spawned process (honest peak memory)."""

from __future__ import annotations

import multiprocessing
import os
import resource
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.features import RaggedFeatures


@dataclass(frozen=True)
class MatchingJob:
    """One protocol pass, sent to a fresh process (everything here pickles)."""

    descriptor: Descriptor
    descriptors_path: str
    positions: np.ndarray
    frame: str
    protocol: int
    exclude: int
    radius: float
    pair_budget: int
    progress: bool


def save_descriptors(stem, descs) -> str:
    """Write a sequence's descriptors for a matching process: ``STEM.npy`` for a stack,
    ``STEM.npz`` (the cache's flat arrays) for feature sets (BEVPlace++, GOSMatch, ...)."""
    if isinstance(descs, RaggedFeatures):
        path = f"{stem}.npz"
        np.savez(path, **descs.to_arrays())
    else:
        path = f"{stem}.npy"
        np.save(path, descs)
    return path


def load_descriptors(path: str):
    """What :func:`save_descriptors` wrote."""
    if str(path).endswith(".npz"):
        with np.load(path) as arrays:
            return RaggedFeatures.from_arrays({k: arrays[k] for k in arrays.files})
    return np.load(path)


def peak_rss_bytes() -> int:
    """Peak resident memory of this process's current address space, in bytes.

    On Linux this is ``VmHWM`` from ``/proc/self/status``, not ``ru_maxrss``:
    the kernel carries a parent's high-water mark into ``ru_maxrss`` across
    fork + exec, so a spawned child reports at least its parent's peak (with
    a 500 MB parent, a fresh child showed ru_maxrss 517 MB but VmHWM 29 MB).
    Elsewhere ``ru_maxrss`` is the best available figure.
    """
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)


def run_matching(job: MatchingJob) -> dict[str, Any]:
    """Run one protocol end to end and measure it (in whatever process calls this).

    Wall time covers ground truth, every distance, and scoring; ``match_s`` is
    the distance computation alone. ``peak_rss_bytes`` is this process's peak
    resident memory (:func:`peak_rss_bytes`), in a fresh process the pass's own.
    """
    from tqdm import tqdm

    from lidar_iris_eval.evaluation.protocol1 import protocol1
    from lidar_iris_eval.evaluation.protocol2 import protocol2

    start = time.perf_counter()
    descs = load_descriptors(job.descriptors_path)
    load_s = time.perf_counter() - start
    start = time.perf_counter()
    job.descriptor.pairwise(descs[:2], descs[:2])  # load compiled kernels
    warmup_s = time.perf_counter() - start
    rss_loaded = peak_rss_bytes()
    n = len(descs)
    rows = n if job.protocol == 2 else max(0, n - job.exclude)
    load = os.getloadavg()
    common = dict(radius=job.radius, frame=job.frame, pair_budget=job.pair_budget)
    with tqdm(total=rows, desc=f"{job.descriptor.name} protocol {job.protocol}", unit="query",
              file=sys.stderr, disable=not job.progress, leave=False) as bar:
        wall, cpu = time.perf_counter(), time.process_time()
        if job.protocol == 1:
            result = protocol1(job.descriptor, descs, job.positions, exclude=job.exclude,
                               progress=bar.update, **common)
            match_s, evaluations = result.matches.seconds, result.matches.n_evaluations
        else:
            result = protocol2(job.descriptor, descs, job.positions, progress=bar.update,
                               **common)
            match_s, evaluations = result.affinity.seconds, result.affinity.n_evaluations
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    keys = ("ap", "f1_max", "r100p", "n_queries", "n_revisits", "n_pairs", "n_positives")
    return {
        "frames": n,
        "wall_s": wall,
        "cpu_s": cpu,
        "match_s": match_s,
        "evaluations": int(evaluations),
        "ordered_pairs": n * (n - 1) if job.protocol == 2 else int(evaluations),
        "load_s": load_s,
        "warmup_s": warmup_s,
        "rss_after_load_bytes": rss_loaded,
        "peak_rss_bytes": peak_rss_bytes(),
        "load_average_at_start": list(load),
        "metrics": {k: result.metrics[k] for k in keys if k in result.metrics},
    }


def run_isolated(job: MatchingJob) -> dict[str, Any]:
    """:func:`run_matching` in a freshly spawned process (spawn, not fork: a forked
    child would share this process's pages and count them as its own)."""
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        return pool.submit(run_matching, job).result()
