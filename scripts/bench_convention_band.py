#!/usr/bin/env python
"""Cost of ``liris eval --convention-band`` against one plain evaluation (issue 38, item 3).

Usage::

    .venv/bin/python scripts/bench_convention_band.py              # small-mixed, quick-start set
    .venv/bin/python scripts/bench_convention_band.py --sequence DIR --repeats 5

Simulates ``small-mixed`` (or opens ``--sequence``), extracts the quick
start's four descriptors once, then times :func:`evaluate` with protocols 1
and 2 (the quick start's run) alternately without and with
``convention_band`` on the same extracted descriptors, in the same process,
``--repeats`` times each; prints the median wall times and their ratio. The
extraction is outside both clocks, so the ratio is that of the evaluations
themselves (the stricter figure: extraction would only dilute it).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

DESCRIPTORS = ("lidar-iris", "scan-context", "m2dp", "esf")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequence", type=Path, default=None)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--protocol", type=int, action="append", default=None)
    parser.add_argument("--cache-dir", type=Path, default=None,
                        help="descriptor cache (extraction is outside the clocks anyway)")
    args = parser.parse_args()
    from lidar_iris_eval.evaluation.evaluate import evaluate
    from lidar_iris_eval.extract import extract_many
    from lidar_iris_eval.io import open_sequence

    with tempfile.TemporaryDirectory() as tmp:
        path = args.sequence
        if path is None:
            from lidar_iris_eval.simulate import simulate_sequence

            path = simulate_sequence(Path(tmp) / "small-mixed", preset="small-mixed")
        seq = open_sequence(path)
        from lidar_iris_eval.descriptors import get_descriptor

        descs = [get_descriptor(name) for name in DESCRIPTORS]
        cache = None
        if args.cache_dir is not None:
            from lidar_iris_eval.cache import DescriptorCache

            cache = DescriptorCache(args.cache_dir)
        dbs = extract_many(seq, descs, cache=cache)
        protocols = tuple(args.protocol or (1, 2))
        evaluate(seq, descs, protocols, dbs=dbs)  # warm-up: compiled kernels, caches
        times = {False: [], True: []}
        cpu = {False: [], True: []}  # process CPU time: less disturbed by other load
        for _ in range(args.repeats):
            for band in (False, True):
                start, start_cpu = time.perf_counter(), time.process_time()
                run = evaluate(seq, descs, protocols, dbs=dbs, convention_band=band)
                times[band].append(time.perf_counter() - start)
                cpu[band].append(time.process_time() - start_cpu)
        plain, banded = statistics.median(times[False]), statistics.median(times[True])
        plain_cpu, banded_cpu = statistics.median(cpu[False]), statistics.median(cpu[True])
        presets = run.rows[0]["convention_band"]["presets"]
        print(f"sequence {seq.name}: {len(seq)} frames, protocols {protocols}, "
              f"descriptors {', '.join(DESCRIPTORS)}")
        print(f"band presets: {', '.join(presets)}")
        print(f"plain evaluation: median {plain:.2f} s of {times[False]}")
        print(f"--convention-band: median {banded:.2f} s of {times[True]}")
        print(f"ratio band / plain (wall): {banded / plain:.3f}")
        print(f"CPU: plain median {plain_cpu:.2f} s, band median {banded_cpu:.2f} s, "
              f"ratio {banded_cpu / plain_cpu:.3f}")


if __name__ == "__main__":
    main()
