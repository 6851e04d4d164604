"""Speed and memory of every descriptor on a KITTI-sized sequence (issue 8).

::

    seq_dir, _ = simulated_sequence(".liris-cache/bench", "kitti-scale", 4541)
    report = run_benchmark(open_sequence(seq_dir), [get_descriptor("lidar-iris")],
                           work_dir=".liris-cache/bench")

Per descriptor the report holds

* **extraction** per scan (median, quartiles, 10/90 % percentiles) as timed
  by :func:`~lidar_iris_eval.extract.extract` in the run that computed the
  descriptors (``from_cache`` says when that was an earlier run);
* **kernel** throughput: wall and CPU time of one ``pairwise`` call of a
  block of queries against the whole database, in pairs per second;
* **loop**: on random pairs, a straightforward per-pair implementation
  written here independently of the descriptor modules (:func:`reference_distance`),
  timed in the same run, with its speed ratio to the kernel; plus the check
  that the batched distances equal (``np.array_equal``) those of the
  single-pair ``distance`` and how far the reference loop's are from them;
* **protocol 1** (exhaustive, each query ``i >= E`` against every ``j <= i - E``)
  and **protocol 2** (the full affinity), each run end to end (ground truth,
  matching, scoring) in a fresh spawned process, so that each pass starts cold
  and the process's peak resident memory (:func:`peak_rss_bytes`) is that of
  the pass alone (interpreter, descriptors, affinity and scoring included).

Numbers are wall-clock on whatever machine runs this, and the load average
is recorded next to them: on a shared machine they are upper bounds.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import platform
import resource
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidar_iris_eval import __version__
from lidar_iris_eval.cache import DescriptorCache
from lidar_iris_eval.config import params_dict
from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.extract import extract
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET

#: descriptors benchmarked by default; Scan Context tries every shift (no pruning)
DEFAULT_DESCRIPTORS = "lidar-iris,scan-context:exhaustive,m2dp,esf"
#: preset used for a descriptor named without one (and without --preset)
DEFAULT_PRESETS = {"scan-context": "exhaustive"}
#: issue 8's bars, valid for a 4541-frame sequence on a 2-core machine
BAR_FRAMES = 4541
BAR_LIDAR_IRIS_PROTOCOL_S = 180.0
BAR_LIDAR_IRIS_PEAK_GIB = 4.0
BAR_SCAN_CONTEXT_PROTOCOL2_S = 120.0
BAR_LIDAR_IRIS_SPEEDUP = 100.0
BAR_LIDAR_IRIS_LOOP_PAIRS = 1000


@dataclass(frozen=True)
class BenchSettings:
    """What to measure and how much of it.

    Attributes
    ----------
    exclude, radius : protocol settings (E frames, positive radius in metres).
    protocols : which protocols to time (1, 2 or both).
    loop_pairs : random pairs for the per-pair loop and the equality check.
    loop_pool : the pairs are drawn among this many random frames, so the
        loop's per-frame preparation (e.g. unpacking LiDAR Iris bits) stays
        small; ``loop_pool**2`` must comfortably exceed ``loop_pairs``.
    kernel_queries, kernel_repeats : block of queries timed against the whole
        database, and how often (the median is kept).
    workers : extraction processes (per-scan times are clean only with 1).
    isolate : run each protocol in a fresh spawned process (honest peak
        memory); False runs them in this process (for quick checks only).
    pair_budget : distances per block of the matching driver.
    seed : random pair selection.
    """

    exclude: int = 30
    radius: float = 4.0
    protocols: tuple[int, ...] = (1, 2)
    loop_pairs: int = 1000
    loop_pool: int = 200
    kernel_queries: int = 128
    kernel_repeats: int = 3
    workers: int = 1
    isolate: bool = True
    pair_budget: int = DEFAULT_PAIR_BUDGET
    seed: int = 0

    def __post_init__(self) -> None:
        checks = [
            ("--exclude", self.exclude >= 1, "must be at least 1"),
            ("--radius", self.radius > 0, "must be positive"),
            ("--loop-pairs", self.loop_pairs >= 0, "must be >= 0"),
            ("--loop-pool", self.loop_pool >= 2, "must be at least 2"),
            ("--kernel-queries", self.kernel_queries >= 1, "must be at least 1"),
            ("--kernel-repeats", self.kernel_repeats >= 1, "must be at least 1"),
            ("--workers", self.workers >= 1, "must be at least 1"),
            ("--block-pairs", self.pair_budget >= 1, "must be at least 1"),
        ]
        for source, ok, problem in checks:
            if not ok:
                raise LirisError(source, problem)
        if not set(self.protocols) <= {1, 2}:
            raise LirisError("protocols", "choose from 1 and 2")


# ----------------------------------------------------------------- the sequence


def simulated_sequence(
    work_dir: str | os.PathLike,
    preset: str = "kitti-scale",
    frames: int | None = None,
    azimuth_steps: int | None = None,
    progress: bool = False,
) -> tuple[Path, float]:
    """A simulated sequence under ``work_dir``, made once and reused afterwards.

    The folder name spells the resolved configuration, and a folder is reused
    only when its ``manifest.json`` (written last by the simulator) records the
    same configuration, so a killed simulation is redone rather than trusted.

    Returns
    -------
    (path, seconds) : the sequence folder and the time spent simulating (0.0
        when an existing one was reused).
    """
    from lidar_iris_eval.simulate import resolve_config, simulate_sequence

    cfg = resolve_config(preset, {"frames": frames, "azimuth_steps": azimuth_steps})
    steps = "full" if cfg.azimuth_steps is None else cfg.azimuth_steps
    path = Path(work_dir) / f"sim-{preset}-n{cfg.frames}-az{steps}"
    if _manifest_matches(path, cfg):
        return path, 0.0
    start = time.perf_counter()
    simulate_sequence(path, preset=preset, overwrite=True, progress=progress,
                      frames=cfg.frames, azimuth_steps=cfg.azimuth_steps)
    return path, time.perf_counter() - start


def _manifest_matches(path: Path, cfg) -> bool:
    manifest = path / "manifest.json"
    if not manifest.is_file():
        return False
    try:
        stored = json.loads(manifest.read_text())
    except (OSError, ValueError):
        return False
    expected = json.loads(json.dumps(dataclasses.asdict(cfg)))  # tuples -> lists
    return stored.get("config") == expected and stored.get("version") == __version__


# -------------------------------------------------------- reference per-pair loops


def lidar_iris_reference(a, b, features_a, features_b, params) -> float:
    """LiDAR Iris distance the slow, obvious way: NumPy on unpacked bool maps.

    Phase correlation from the stored row spectra (a complex exponential per
    harmonic and column), then ``np.roll`` of the query's maps for every shift
    of the window and a masked Hamming count. ``features_*`` are
    ``binary_features(image)`` of each descriptor (recomputed from the image,
    not unpacked from the stored bits).
    """
    (t1, m1), (t2, m2) = features_a, features_b
    f1 = a["spec_re"].astype(np.float64) + 1j * a["spec_im"].astype(np.float64)
    f2 = b["spec_re"].astype(np.float64) + 1j * b["spec_im"].astype(np.float64)
    cross = (f1 * np.conj(f2)).sum(axis=0)
    size = np.abs(cross)
    unit = np.divide(cross, size, out=np.zeros_like(cross), where=size > 0)
    n = params.sectors
    k = np.arange(1, len(unit) + 1)[:, None]
    surface = np.real(unit[:, None] * np.exp(-2j * np.pi * k * np.arange(n)[None, :] / n)).sum(0)
    centre = int(np.argmax(surface))
    centres = {"same": [centre], "reverse": [centre + n // 2],
               "both": [centre, centre + n // 2]}[params.match_mode]
    best = np.nan
    for c in centres:
        for shift in range(c - params.shift_window, c + params.shift_window + 1):
            mask = np.roll(m1, shift, axis=1) | m2
            valid = (~mask).sum()
            if valid == 0:
                continue
            d = ((np.roll(t1, shift, axis=1) ^ t2) & ~mask).sum() / valid
            if np.isnan(best) or d < best:
                best = d
    return float(best)


def scan_context_reference(q, c, params) -> float:
    """Scan Context distance as the authors' code describes it, in float64 NumPy.

    For each tried shift the candidate is rolled, and ``1 - cos`` is averaged
    over the columns non-empty in both (or summed and divided by the number of
    sectors for ``divide_by: sectors``); the minimum over shifts is returned.
    ``sector-key`` tries ``+-search_radius`` around the shift that best aligns
    the sector keys (column means), ``exhaustive`` every shift.
    """
    q = np.asarray(q["sc"], dtype=np.float64)
    c = np.asarray(c["sc"], dtype=np.float64)
    n = q.shape[1]
    if params.search == "exhaustive":
        shifts = range(n)
    else:
        vq, vc = q.mean(axis=0), c.mean(axis=0)
        start = int(np.argmin([np.linalg.norm(vq - np.roll(vc, s)) for s in range(n)]))
        r = params.search_radius
        shifts = sorted({(start + j) % n for j in range(-r, r + 1)})
    norm_q = np.linalg.norm(q, axis=0)
    best = np.nan
    for s in shifts:
        cs = np.roll(c, s, axis=1)
        norm_c = np.linalg.norm(cs, axis=0)
        valid = (norm_q > 0) & (norm_c > 0)
        if not valid.any():
            continue
        cos = (q * cs).sum(axis=0)[valid] / (norm_q * norm_c)[valid]
        d = 1.0 - (cos.sum() / n if params.divide_by == "sectors" else cos.mean())
        if np.isnan(best) or d < best:
            best = d
    return float(best)


def m2dp_reference(a, b, params=None) -> float:
    """Euclidean distance of two M2DP vectors."""
    return float(np.linalg.norm(np.asarray(a, np.float64) - np.asarray(b, np.float64)))


def esf_reference(a, b, params=None) -> float:
    """L1 distance of two ESF histograms."""
    return float(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).sum())


def _iris_features(desc: Descriptor, record):
    from lidar_iris_eval.descriptors.lidar_iris import binary_features

    return binary_features(record["image"], desc.params)


def reference_loop(desc: Descriptor, descs: np.ndarray, pairs: np.ndarray):
    """Distances of ``pairs`` by the reference per-pair implementation, and its time.

    Per-frame preparation that a real database would store once (LiDAR Iris's
    unpacked maps) is done before the clock starts; the timed part is a plain
    Python loop calling the single-pair formula.

    Returns
    -------
    (distances, seconds, cpu_seconds) or None when no reference exists for
    this descriptor.
    """
    if desc.name == "lidar-iris":
        frames = np.unique(pairs)
        feats = {int(i): _iris_features(desc, descs[i]) for i in frames}

        def one(i, j):
            return lidar_iris_reference(descs[i], descs[j], feats[i], feats[j], desc.params)
    elif desc.name in _PLAIN_REFERENCES:
        formula = _PLAIN_REFERENCES[desc.name]

        def one(i, j):
            return formula(descs[i], descs[j], desc.params)
    else:
        return None
    wall, cpu = time.perf_counter(), time.process_time()
    out = np.array([one(int(i), int(j)) for i, j in pairs], dtype=np.float64)
    return out, time.perf_counter() - wall, time.process_time() - cpu


_PLAIN_REFERENCES: dict[str, Callable] = {
    "scan-context": scan_context_reference,
    "m2dp": m2dp_reference,
    "esf": esf_reference,
}


def reference_distance(desc: Descriptor, a, b) -> float:
    """The reference per-pair distance of two descriptors (no yaw), for spot checks."""
    if desc.name == "lidar-iris":
        return lidar_iris_reference(a, b, _iris_features(desc, a), _iris_features(desc, b),
                                    desc.params)
    if desc.name not in _PLAIN_REFERENCES:
        raise LirisError(f"--descriptor {desc.name}", "no reference per-pair implementation")
    return _PLAIN_REFERENCES[desc.name](a, b, desc.params)


# ------------------------------------------------------------------ measurements


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


def extraction_summary(db) -> dict[str, Any]:
    """Per-scan ``compute`` time statistics in milliseconds."""
    ms = np.asarray(db.extract_s, dtype=np.float64) * 1e3
    p10, q1, med, q3, p90 = np.percentile(ms, [10, 25, 50, 75, 90])
    return {
        "scans": len(ms), "median_ms": med, "q1_ms": q1, "q3_ms": q3, "p10_ms": p10,
        "p90_ms": p90, "mean_ms": float(ms.mean()), "max_ms": float(ms.max()),
        "read_median_ms": float(np.median(db.read_s) * 1e3), "from_cache": db.from_cache,
        "descriptor_bytes": int(db.descriptors.nbytes // max(1, len(db))),
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


# ------------------------------------------------------- protocols in a fresh process


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
    descs = np.load(job.descriptors_path)
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


# ------------------------------------------------------------------- the benchmark


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
    path = scratch / f"{desc.name}-{os.getpid()}.npy"
    np.save(path, descs)
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


# ---------------------------------------------------------------- bars and summary


def evaluate_bars(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 8's bars that this report can judge (only for a 4541-frame sequence)."""
    if report["sequence"]["frames"] != BAR_FRAMES:
        return []
    bars = []

    def bar(what, value, limit, met):
        bars.append({"bar": what, "value": value, "limit": limit, "met": bool(met)})

    for e in report["descriptors"]:
        if e["descriptor"] == "lidar-iris":
            for p in (1, 2):
                if f"protocol{p}" in e:
                    wall = e[f"protocol{p}"]["wall_s"]
                    bar(f"lidar-iris protocol {p} wall s", wall, BAR_LIDAR_IRIS_PROTOCOL_S,
                        wall <= BAR_LIDAR_IRIS_PROTOCOL_S)
            peaks = [e[f"protocol{p}"]["peak_rss_bytes"] for p in (1, 2)
                     if f"protocol{p}" in e and e[f"protocol{p}"]["isolated"]]
            if peaks:
                gib = max(peaks) / 2**30
                bar("lidar-iris peak memory GiB", gib, BAR_LIDAR_IRIS_PEAK_GIB,
                    gib <= BAR_LIDAR_IRIS_PEAK_GIB)
            ref = (e.get("loop") or {}).get("reference")
            if ref is not None:
                bar("lidar-iris kernel speedup over per-pair loop", ref["speedup"],
                    BAR_LIDAR_IRIS_SPEEDUP, ref["speedup"] >= BAR_LIDAR_IRIS_SPEEDUP)
                n = e["loop"]["pairs"]
                bar("lidar-iris loop distances identical (pairs)", n,
                    BAR_LIDAR_IRIS_LOOP_PAIRS, ref["identical"] and n >= BAR_LIDAR_IRIS_LOOP_PAIRS)
        if (e["descriptor"] == "scan-context" and e["params"].get("search") == "exhaustive"
                and "protocol2" in e):
            wall = e["protocol2"]["wall_s"]
            bar("scan-context exhaustive protocol 2 wall s", wall, BAR_SCAN_CONTEXT_PROTOCOL2_S,
                wall <= BAR_SCAN_CONTEXT_PROTOCOL2_S)
    return bars


def summary_rows(report: dict[str, Any]) -> list[dict[str, Any]]:
    """One table row per descriptor with the headline figures."""
    rows = []
    for e in report["descriptors"]:
        ex, kernel = e["extraction"], e["kernel"]
        loop = e.get("loop") or {}
        ref = loop.get("reference") or {}
        peaks = [e[k]["peak_rss_bytes"] for k in ("protocol1", "protocol2") if k in e]
        rows.append({
            "descriptor": f"{e['descriptor']}:{e['preset']}",
            "extract_ms_med": ex["median_ms"],
            "extract_ms_iqr": f"{ex['q1_ms']:.1f}-{ex['q3_ms']:.1f}",
            "kernel_pairs_per_s": float(kernel["pairs_per_s"]),
            "loop_speedup": ref.get("speedup", float("nan")),
            "batched==single": loop.get("batched_equals_single", "-"),
            "loop_identical": ref.get("identical", "-"),
            "p1_wall_s": e.get("protocol1", {}).get("wall_s", float("nan")),
            "p2_wall_s": e.get("protocol2", {}).get("wall_s", float("nan")),
            "peak_gib": max(peaks) / 2**30 if peaks else float("nan"),
        })
    return rows
