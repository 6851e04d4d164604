"""Speed and memory of every descriptor on a KITTI-sized sequence (issues 8 and 18).

::

    seq_dir, _ = simulated_sequence(".liris-cache/bench", "kitti-scale", 4541)
    report = run_benchmark(open_sequence(seq_dir), [get_descriptor("lidar-iris")],
                           work_dir=".liris-cache/bench")

One module per job:

* :mod:`.settings` — what to measure (:class:`BenchSettings`) and the bars' limits;
* :mod:`.sequence` — the simulated sequence, made once and reused;
* :mod:`.measure` — extraction statistics, kernel throughput, batched vs
  single-pair vs reference loop, machine information;
* :mod:`.references` — looks up each descriptor's own per-pair reference loop
  (``descriptors/<name>/reference_loop.py``) and times it;
* :mod:`.extraction` — extraction per full-resolution scan and single-pair
  time next to the authors' C++ figures, as ratios;
* :mod:`.isolate` — one protocol pass in a freshly spawned process, with its
  own peak resident memory;
* :mod:`.bars` — pass/fail bars and the summary table;
* :mod:`.run` — the run that ties them together (:func:`run_benchmark`).

Numbers are wall-clock on whatever machine runs this, and the load average
is recorded next to them: on a shared machine they are upper bounds.
"""

from lidar_iris_eval.bench.bars import evaluate_bars, summary_rows
from lidar_iris_eval.bench.isolate import MatchingJob, peak_rss_bytes, run_isolated, run_matching
from lidar_iris_eval.bench.measure import (
    extraction_summary,
    kernel_throughput,
    loop_comparison,
    machine_info,
    points_per_scan,
    sample_pairs,
)
from lidar_iris_eval.bench.references import (
    esf_reference,
    lidar_iris_reference,
    m2dp_reference,
    reference_distance,
    reference_loop,
    scan_context_reference,
)
from lidar_iris_eval.bench.run import bench_descriptor, run_benchmark
from lidar_iris_eval.bench.sequence import simulated_sequence
from lidar_iris_eval.bench.settings import DEFAULT_DESCRIPTORS, DEFAULT_PRESETS, BenchSettings

__all__ = [
    "DEFAULT_DESCRIPTORS",
    "DEFAULT_PRESETS",
    "BenchSettings",
    "MatchingJob",
    "bench_descriptor",
    "esf_reference",
    "evaluate_bars",
    "extraction_summary",
    "kernel_throughput",
    "lidar_iris_reference",
    "loop_comparison",
    "m2dp_reference",
    "machine_info",
    "peak_rss_bytes",
    "points_per_scan",
    "reference_distance",
    "reference_loop",
    "run_benchmark",
    "run_isolated",
    "run_matching",
    "sample_pairs",
    "scan_context_reference",
    "simulated_sequence",
    "summary_rows",
]
