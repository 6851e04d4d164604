#!/usr/bin/env python
"""Time the all-pairs matching pass (protocols 1 and 2 in one pass) at KITTI-00 size.

Usage::

    nice -n 19 python scripts/bench_matching.py --world W --frames 4541 \\
        -d scan-context,m2dp,esf --workers 2 --cache-dir C

The descriptors of a simulated world (``liris simulate``) are extracted once
into ``--cache-dir`` and stacked up to ``--frames`` rows: the world's own rows,
then copies scaled by a random factor in ``[0.99, 1.01]`` (LiDAR Iris copies
are exact repeats: its bits cannot be scaled), so a 600-frame world stands in
for the 4541 frames of KITTI 00 without simulating 12 GB. Positions are a
seeded random walk, E = 30. Each descriptor's pass
(``streaming_pr.stream_protocol2`` with protocol 1's limits) is run under the
executor of ``--workers`` (:func:`~lidar_iris_eval.executor.local_executor`)
and reported as wall and process CPU time, distances evaluated and a SHA-256
of its results (PR curve, best matches), so two versions of the code can be
compared on the same machine (``PYTHONPATH``) and checked equal.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import resource
import time

import numpy as np

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
from lidar_iris_eval.evaluation.streaming_pr import stream_protocol2
from lidar_iris_eval.executor import local_executor
from lidar_iris_eval.extract import extract_many
from lidar_iris_eval.io import open_sequence


def stacked(x: np.ndarray, frames: int, seed: int = 0) -> np.ndarray:
    """``x`` repeated to ``frames`` rows; copies beyond the first scaled by 1 +- 1 %."""
    if frames <= len(x):
        return x[:frames]
    rng = np.random.default_rng(seed)
    out = np.concatenate([x] * -(-frames // len(x)))[:frames].copy()
    tail = out[len(x):]
    if out.dtype.names is None:
        tail *= rng.uniform(0.99, 1.01, tail.shape).astype(out.dtype)
    elif "sc" in out.dtype.names:  # Scan Context: its polar context
        tail["sc"] *= rng.uniform(0.99, 1.01, tail["sc"].shape).astype(tail["sc"].dtype)
    return out


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _digest(curve, best) -> str:
    h = hashlib.sha256()
    for a in (curve.precision, curve.recall, best.query, best.match, best.distance, best.yaw_deg):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--world", required=True)
    ap.add_argument("--frames", type=int, default=4541)
    ap.add_argument("-d", "--descriptors", default="scan-context,m2dp,esf")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cache-dir", required=True)
    ap.add_argument("--json-out")
    args = ap.parse_args()
    seq = open_sequence(args.world)
    descs = [get_descriptor(name) for name in args.descriptors.split(",")]
    dbs = extract_many(seq, descs, cache=args.cache_dir, workers=1)
    rng = np.random.default_rng(0)
    positions = np.cumsum(rng.normal(size=(args.frames, 3)), axis=0)
    gt = compute_ground_truth(positions, 4.0, 1)
    executor = local_executor(args.workers)
    out = {"frames": args.frames, "workers": args.workers, "load_average": os.getloadavg(),
           "results": {}}
    for desc, db in zip(descs, dbs, strict=True):
        x = stacked(db.descriptors, args.frames)
        desc.pairwise(x[:1], x[:2])  # compile / load the kernels before the clock
        wall, cpu = time.perf_counter(), _cpu()
        aff, curve, best = stream_protocol2(desc, x, gt.pairs, gt.n_positive_pairs, 30, None,
                                            None, "none", executor)
        row = {"wall_s": time.perf_counter() - wall, "cpu_s": _cpu() - cpu,
               "evaluations": int(aff.n_evaluations), "sha256": _digest(curve, best)}
        out["results"][desc.name] = row
        print(f"{desc.name}: wall {row['wall_s']:.2f} s, CPU {row['cpu_s']:.2f} s, "
              f"{row['evaluations']} distances, {row['sha256'][:12]}", flush=True)
    out["load_average_end"] = os.getloadavg()
    if args.json_out:
        with open(args.json_out, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
