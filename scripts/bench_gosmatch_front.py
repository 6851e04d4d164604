#!/usr/bin/env python
"""GOSMatch front end (labels -> objects) per scan: SciPy components vs union-find, one run.

Usage::

    OMP_NUM_THREADS=1 nice -n 10 python scripts/bench_gosmatch_front.py SEQ --every 5

``SEQ`` is a sequence with labels (``liris simulate`` writes them). For every
``--every``-th scan, ``objects_from_labels`` runs with the components of
``scipy.sparse.csgraph.connected_components`` (the code before issue 41) and with
the compiled union-find (now), alternating per scan; thread CPU time per scan
(median, ms) of each and whether every scan's objects are bitwise equal.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from lidar_iris_eval.descriptors.gosmatch import semantics
from lidar_iris_eval.io import open_sequence


def scipy_components(n: int, pairs: np.ndarray) -> np.ndarray:
    graph = coo_matrix((np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])),
                       shape=(n, n))
    return connected_components(graph, directed=False)[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--every", type=int, default=5)
    args = ap.parse_args()
    seq = open_sequence(args.sequence)
    settings = semantics.ClusterSettings()
    scans = [seq.read(i, {"labels"}) for i in range(0, len(seq), args.every)]
    fast = semantics._components
    fast(2, np.zeros((1, 2), dtype=np.int64))  # compile outside the timing
    times = {"scipy": [], "union_find": []}
    same = True
    for scan in scans:
        out = {}
        for name, fn in (("scipy", scipy_components), ("union_find", fast)):
            semantics._components = fn
            t0 = time.thread_time()
            out[name] = semantics.objects_from_labels(scan.points, scan.labels, settings)
            times[name].append(time.thread_time() - t0)
        semantics._components = fast
        same &= all(np.array_equal(a, b) for a, b in zip(out["scipy"], out["union_find"],
                                                             strict=True))
    med = {k: round(float(np.median(v)) * 1e3, 2) for k, v in times.items()}
    print(json.dumps({"sequence": args.sequence, "scans": len(scans),
                      "points_per_scan": int(np.median([len(s.points) for s in scans])),
                      "ms_per_scan_median": med,
                      "ratio_scipy_over_union_find": round(med["scipy"] / med["union_find"], 2),
                      "identical_objects": bool(same), "load": os.getloadavg()}, indent=1))


if __name__ == "__main__":
    main()
