#!/usr/bin/env python
"""Matching cost of the learned vector descriptors at KITTI-00 length: Gram vs broadcast.

Usage::

    OMP_NUM_THREADS=1 python scripts/bench_learned_matching.py [--frames 4541]
        [--queries 64] [--rounds 3] [--full] [--json FILE]

``N`` random unit float32 vectors of 256 (OverlapTransformer) and 8192
(BEVPlace++) dimensions stand in for a sequence's descriptors (matching cost
does not depend on their values). Each round times ``pairwise`` of a block of
queries against all ``N`` frames by the current route
(:func:`~lidar_iris_eval.descriptors.vector_common.gram_pairwise`, what
``LearnedVectorDescriptor`` uses) and by the previous one (the broadcast
difference :func:`~lidar_iris_eval.descriptors.vector_common.vector_rows` in
:func:`~lidar_iris_eval.descriptors.vector_common.pairwise_blocks`), alternating,
in one process with one BLAS thread. The current route gets the block
the matching driver would give it (``block_rows(N)``: 230 queries at N = 4541),
the previous one ``--queries`` (it loops over single queries at 8192-d anyway,
so its cost per pair does not depend on the block); the ratio previous / current of the
medians is the speed-up, and both are extrapolated to protocol 2's ``N (N - 1)
/ 2`` distances (a symmetric method computes the lower triangle once) and
protocol 1's ``(N - E)(N - E + 1) / 2`` (E = 30). ``--full`` also times the
current route on the whole ``N x N`` matrix once (the previous one would take
tens of minutes at 8192-d).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from lidar_iris_eval.descriptors.vector_common import (  # noqa: E402
    gram_pairwise,
    pairwise_blocks,
    vector_rows,
)
from lidar_iris_eval.matching.blocks import block_rows  # noqa: E402


def unit_rows(rng, n: int, width: int) -> np.ndarray:
    x = rng.normal(size=(n, width))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def timed(fn, *args) -> tuple[float, float, np.ndarray]:
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args)
    return time.perf_counter() - wall, time.process_time() - cpu, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=4541)
    ap.add_argument("--queries", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--exclude", type=int, default=30)
    ap.add_argument("--widths", default="256,8192")
    ap.add_argument("--full", action="store_true")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    n, e = args.frames, args.exclude
    p2_pairs = n * (n - 1) // 2
    p1_pairs = (n - e) * (n - e + 1) // 2
    report = {"frames": n, "queries_broadcast": args.queries, "queries_gram": block_rows(n),
              "rounds": args.rounds,
              "threads": os.environ.get("OMP_NUM_THREADS"), "widths": {}}
    for width in (int(w) for w in args.widths.split(",")):
        descs = unit_rows(rng, n, width)
        block = descs[: args.queries]
        big = descs[: block_rows(n)]
        gram_pairwise(descs[:2], descs[:2])
        new, old, new_cpu, old_cpu, diff = [], [], [], [], 0.0
        for _ in range(args.rounds):
            w, c, d_big = timed(gram_pairwise, big, descs)
            new.append(w / len(big) * len(block))
            c = c / len(big) * len(block)
            d_new = d_big[: len(block)]
            new_cpu.append(c)
            w, c, d_old = timed(pairwise_blocks, vector_rows, block, descs)
            d_old = d_old[0]
            old.append(w)
            old_cpu.append(c)
            diff = max(diff, float(np.abs(d_new - d_old).max()))
            same_top1 = bool(np.array_equal(np.argmin(d_new, 1), np.argmin(d_old, 1)))
        pairs = len(block) * n  # times are per len(block) queries (the Gram's rescaled)
        entry = {
            "gram_s": float(np.median(new)), "broadcast_s": float(np.median(old)),
            "gram_cpu_s": float(np.median(new_cpu)), "broadcast_cpu_s": float(np.median(old_cpu)),
            "ratio_rounds": [o / g for o, g in zip(old, new, strict=True)],
            "speedup": float(np.median(old) / np.median(new)),
            "gram_us_per_pair": 1e6 * float(np.median(new)) / pairs,
            "broadcast_us_per_pair": 1e6 * float(np.median(old)) / pairs,
            "max_abs_diff": diff, "same_top1": same_top1,
        }
        for key in ("gram", "broadcast"):
            per = entry[f"{key}_us_per_pair"] * 1e-6
            entry[f"{key}_protocol2_s_est"] = per * p2_pairs
            entry[f"{key}_protocol1_s_est"] = per * p1_pairs
        if args.full:
            w, c, _ = timed(gram_pairwise, descs, descs)
            entry["gram_full_matrix_s"], entry["gram_full_matrix_cpu_s"] = w, c
        report["widths"][str(width)] = entry
        print(f"{width:5d}-d  gram {entry['gram_us_per_pair']:.3f} us/pair  broadcast "
              f"{entry['broadcast_us_per_pair']:.3f} us/pair  speed-up x{entry['speedup']:.1f} "
              f"(rounds {', '.join(f'{r:.1f}' for r in entry['ratio_rounds'])})  "
              f"protocol 2 est. {entry['gram_protocol2_s_est']:.1f} s vs "
              f"{entry['broadcast_protocol2_s_est']:.0f} s  max |diff| {diff:.2e}  "
              f"top-1 same {same_top1}"
              + (f"  full {n}x{n}: {entry['gram_full_matrix_s']:.1f} s" if args.full else ""),
              flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(report, fh, indent=2)


if __name__ == "__main__":
    main()
