#!/usr/bin/env python
"""Bytes read by extraction before and after issue 41 item 7 (declared inputs), in one run.

Usage::

    OMP_NUM_THREADS=1 nice -n 10 python scripts/bench_inputs.py SEQ -d scan-context,m2dp

``SEQ`` is a sequence with a ``labels/`` folder (``liris simulate`` writes one). For the
code of ``--before-ref`` (default ``main``, exported from git into a temporary folder)
and for this tree, a child process extracts ``-d`` on every scan (no cache, one
process) and reports from ``/proc/self/io`` the bytes it read (``rchar``: every
``read`` call, page cache or not), its wall time and a SHA-256 of the descriptors, so
the two are compared on identical results. The label and point files' sizes on disk
are printed beside.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import hashlib, json, sys, time
import numpy as np
from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.extract import extract_many
from lidar_iris_eval.io import open_sequence

def io():
    return {k: int(v) for k, v in (line.split(": ") for line in open("/proc/self/io"))}

seq = open_sequence(sys.argv[1])
descs = [get_descriptor(n) for n in sys.argv[2].split(",")]
before, t0 = io(), time.perf_counter()
dbs = extract_many(seq, descs, cache=None, workers=1)
wall, after = time.perf_counter() - t0, io()
digest = hashlib.sha256()
for db in dbs:
    digest.update(np.ascontiguousarray(db.descriptors).tobytes())
print(json.dumps({"rchar": after["rchar"] - before["rchar"], "wall_s": round(wall, 2),
                  "read_s": round(float(sum(db.read_s.sum() for db in dbs[:1])), 2),
                  "digest": digest.hexdigest()}))
"""


def run(source: Path, seq: str, names: str) -> dict:
    out = subprocess.run([sys.executable, "-c", f"import sys; sys.path.insert(0, {str(source)!r})"
                          f"\n{CHILD}", seq, names], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("-d", "--descriptors", default="scan-context,m2dp")
    ap.add_argument("--before-ref", default="main")
    args = ap.parse_args()
    seq = Path(args.sequence)
    sizes = {kind: sum(p.stat().st_size for p in (seq / kind).iterdir())
             for kind in ("velodyne", "labels") if (seq / kind).is_dir()}
    with tempfile.TemporaryDirectory() as tmp:
        archive = subprocess.run(["git", "-C", str(ROOT), "archive", args.before_ref,
                                  "lidar_iris_eval"], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", tmp], input=archive, check=True)
        before = run(Path(tmp), str(seq), args.descriptors)
    after = run(ROOT, str(seq), args.descriptors)
    report = {"sequence": str(seq), "descriptors": args.descriptors, "bytes_on_disk": sizes,
              "before": before, "after": after,
              "identical_descriptors": before["digest"] == after["digest"],
              "bytes_read_ratio_after_over_before": round(after["rchar"] / before["rchar"], 3)}
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
