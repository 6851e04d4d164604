#!/usr/bin/env python
"""Registration (``--refine gicp``) before and after issue 41, in one run, on one sequence.

Usage::

    OMP_NUM_THREADS=1 nice -n 10 python scripts/bench_registration.py /tmp/small --json-out r.json
    python scripts/bench_registration.py SEQ --max-loops 60 --gt-pose refined

``SEQ`` is any sequence ``liris eval`` opens (default: ``small-mixed``, the README's
quick-start sequence, simulated into a temporary folder). The loops are the protocol 1
top-1 matches of ``-d`` (default ``lidar-iris``), with that method's pose as the
initial guess, exactly as ``liris eval SEQ --protocol 1 --refine gicp`` registers them.

Three ways register the same loops, one after the other in this process:

* ``before``: the registration module of ``--before-ref`` (default ``main``), loaded
  from git: serial, one pass at a time, an LRU of 256 prepared scans;
* ``serial``: this version with ``--workers 1``;
* ``parallel``: this version with ``--workers`` processes (default 2).

``--repeat R`` runs the three R times, interleaved (before, serial, parallel, before, ...),
and the ratio uses the median wall of each, so a change of load during the run hits
all three alike. Recorded: wall and CPU (this process and its children) of each (first
round), ms per loop (the
alignment's own time, mean), ms per prepared scan and the number of scans prepared
(against the number of distinct scans), the ratios ``before / parallel``, and whether
the refined poses are bitwise equal to ``before``'s. On a shared machine every time is
contended: the load average before and after is recorded.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _cpu() -> float:
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def load_before(ref: str):
    """The registration module of git ``ref``, imported under another name."""
    source = subprocess.run(["git", "-C", str(ROOT), "show",
                             f"{ref}:lidar_iris_eval/matching/registration.py"],
                            check=True, capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "registration_before.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("registration_before", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def loops(seq, descriptor: str, cache_dir: str | None, max_loops: int | None, gt_pose: str):
    """``[(query, match, initial)]`` per pass, as ``liris eval --refine gicp`` builds them."""
    from lidar_iris_eval.evaluation.evaluate import evaluate
    from lidar_iris_eval.evaluation.poses import relative_ground_truth

    ev = evaluate(seq, [descriptor], protocols=(1,), cache=cache_dir)
    p1 = ev.results[0].protocol1
    q, m = p1.matches.query, p1.matches.match
    pose = p1.pose if p1.pose is not None else np.full((len(q), 4, 4), np.nan)
    keep = slice(None) if max_loops is None else np.flatnonzero(m >= 0)[:max_loops]
    passes = [(q[keep], m[keep], pose[keep])]
    if gt_pose == "refined":
        true = np.asarray(p1.is_true, dtype=bool)[keep]
        gt = relative_ground_truth(seq.poses, q[keep], m[keep])
        passes.append((q[keep], np.where(true, m[keep], -1), gt))
    return passes


def run_before(module, seq, passes):
    settings = module.RegistrationSettings()
    cache = module.ScanCache(seq, settings)
    return [module.refine_pairs(seq, q, m, init, settings, cache=cache)
            for q, m, init in passes], cache.n_prepared, cache.prepare_s


def run_now(seq, passes, workers: int):
    from lidar_iris_eval.executor import local_executor
    from lidar_iris_eval.matching.registration import RegistrationSettings, ScanCache, refine_many

    settings = RegistrationSettings()
    cache = ScanCache(seq, settings)
    out = refine_many(seq, passes, settings, cache=cache, executor=local_executor(workers))
    return out, cache.n_prepared, cache.prepare_s


def timed(fn, *args):
    wall0, cpu0 = time.perf_counter(), _cpu()
    result = fn(*args)
    return result, time.perf_counter() - wall0, _cpu() - cpu0


def summary(name, result, wall, cpu, n_loops, n_distinct) -> dict:
    refined, n_prepared, prepare_s = result
    secs = np.concatenate([r.seconds for r in refined])
    secs = secs[np.isfinite(secs)]
    return {"way": name, "wall_s": round(wall, 2), "cpu_s": round(cpu, 2),
            "loops": n_loops, "ms_per_loop_align": round(float(np.mean(secs)) * 1e3, 1),
            "ms_per_loop_wall": round(wall / max(1, n_loops) * 1e3, 1),
            "scans_prepared": int(n_prepared), "distinct_scans": int(n_distinct),
            "ms_per_scan_prepare": round(prepare_s / max(1, n_prepared) * 1e3, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequence", nargs="?", help="a sequence (default: small-mixed, simulated)")
    ap.add_argument("-d", "--descriptor", default="lidar-iris")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--max-loops", type=int, default=None, help="register only the first N")
    ap.add_argument("--gt-pose", choices=("dataset", "refined"), default="dataset")
    ap.add_argument("--before-ref", default="main", help="git ref of the 'before' code")
    ap.add_argument("--skip-before", action="store_true")
    ap.add_argument("--prepare-only", action="store_true",
                    help="only count the scans prepared (serial, --workers); no alignment")
    ap.add_argument("--repeat", type=int, default=1,
                    help="rounds of the ways, interleaved (median wall per way)")
    ap.add_argument("--cache-dir", default=None)
    ap.add_argument("--json-out", default=None)
    args = ap.parse_args()
    from lidar_iris_eval.io import open_sequence

    if args.sequence is None:
        from lidar_iris_eval.simulate import simulate_sequence

        args.sequence = str(Path(tempfile.mkdtemp()) / "small-mixed")
        simulate_sequence(args.sequence, preset="small-mixed")
    seq = open_sequence(args.sequence)
    passes = loops(seq, args.descriptor, args.cache_dir, args.max_loops, args.gt_pose)
    n_loops = sum(int(np.count_nonzero(m >= 0)) for _, m, _ in passes)
    distinct = set()
    for q, m, _ in passes:
        distinct |= set(q[m >= 0].tolist()) | set(m[m >= 0].tolist())
    if args.prepare_only:  # count preparations: every alignment replaced by a failed one
        from lidar_iris_eval.matching import registration as reg

        reg.register = lambda target, source, initial, settings: reg.failed()
        counts = {f"workers_{w}": run_now(seq, passes, w)[1] for w in (1, args.workers)}
        print(json.dumps({"loops": n_loops, "distinct_scans": len(distinct),
                          "scans_prepared": counts}, indent=1))
        return
    report = {"sequence": args.sequence, "descriptor": args.descriptor, "loops": n_loops,
              "workers": args.workers, "load_before": os.getloadavg(), "ways": []}
    results = {}
    ways = [("serial", run_now, (seq, passes, 1)),
            ("parallel", run_now, (seq, passes, args.workers))]
    if not args.skip_before:
        ways.insert(0, ("before", run_before, (load_before(args.before_ref), seq, passes)))
    walls: dict[str, list[float]] = {name: [] for name, _, _ in ways}
    for round_ in range(args.repeat):  # interleaved, so a change of load hits every way alike
        for name, fn, fn_args in ways:
            result, wall, cpu = timed(fn, *fn_args)
            walls[name].append(wall)
            if round_ == 0:
                results[name] = result[0]
                report["ways"].append(summary(name, result, wall, cpu, n_loops, len(distinct)))
            print(json.dumps({"round": round_, "way": name, "wall_s": round(wall, 2),
                              "cpu_s": round(cpu, 2)}), file=sys.stderr)
    for w in report["ways"]:
        w["wall_s_rounds"] = [round(x, 2) for x in walls[w["way"]]]
        w["wall_s_median"] = round(float(np.median(walls[w["way"]])), 2)
    reference = results.get("before", results["serial"])
    report["identical_poses"] = {
        name: all(np.array_equal(a.pose, b.pose, equal_nan=True)
                  and np.array_equal(a.inlier_ratio, b.inlier_ratio, equal_nan=True)
                  for a, b in zip(reference, refined, strict=True))
        for name, refined in results.items()}
    by = {w["way"]: w for w in report["ways"]}
    base = by.get("before", by["serial"])
    report["ratio_wall_base_over_parallel"] = round(base["wall_s_median"]
                                                    / by["parallel"]["wall_s_median"], 2)
    report["ratio_scans_prepared_base_over_parallel"] = round(
        base["scans_prepared"] / max(1, by["parallel"]["scans_prepared"]), 2)
    report["load_after"] = os.getloadavg()
    text = json.dumps(report, indent=1)
    if args.json_out:
        Path(args.json_out).write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    main()
