"""GOSMatch: parameter sweep on simulated sequences, and protocol-1 speed at KITTI scale.

Three jobs, all outside the test suite:

``sweep SEQ``
    Protocol 1 (E = 30, 4 m, ``revisits`` recall) on a *simulated* sequence with
    labels, over a grid of the parameters neither the paper nor the authors' code
    fixes: clustering tolerance and minimum size, candidates N, RANSAC iterations,
    inlier threshold, minimum inliers, score, and RANSAC seeds. Objects are
    clustered once per front-end setting; matching is repeated per setting.
    Also counts the simulator's objects against its car instance ids.

``speed OBJECTS --poses P --calib C``
    Protocol 1 on the authors' object layout (all 4541 KITTI 00 scans) through
    the pipeline's own path (``extract`` without cache, then
    ``two_stage_matches``), wall and CPU time of each stage after compiling the
    kernels, plus the compiled verification against the NumPy reference
    (``GOSMatch.verify_reference`` around ``geometry.ransac_rigid``) on a sample
    of queries in the same run. Matching runs on one thread; ``--processes 2``
    also times it with the queries dealt to 2 forked processes (the same
    per-query steps; the matches are checked identical to the pipeline's).

``census SEQ``
    Why a world gives GOSMatch few or no matches: over every ``--every``-th
    scan of a sequence with labels, the labelled points of each object class
    (vehicle, trunk, pole), the objects the front end keeps per scan, how many
    scans reach the ``min_inliers`` objects verification needs (a scan with
    fewer can never be accepted, as query or as candidate), and where the
    trunk points lie (median range; the share in clusters the front end
    keeps). JSON on stdout.

The machine may be shared: the report holds the load average before and after.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.descriptors.gosmatch import GOSMatch
from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
from lidar_iris_eval.evaluation.protocol1 import score_protocol1
from lidar_iris_eval.matching.blocks import BestMatches
from lidar_iris_eval.matching.geometry import (
    invert_pose,
    rotation_error_deg,
    translation_error_m,
)


def load_sequence(path: str, poses: str | None, calib: str | None):
    """An object layout or a KITTI-layout sequence with labels."""
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.io.objects import is_objects_layout, open_objects

    if is_objects_layout(path):
        return open_objects(path, poses=poses, calib=calib)
    return open_sequence(path, poses=poses, calib=calib)


class _LabelledScan:
    """Points and labels of a KITTI-layout scan (read here, independent of io/ changes)."""

    def __init__(self, seq, i: int):
        path = seq.scan_paths[i]
        self.points = np.fromfile(path, dtype=np.float32).reshape(-1, 4)[:, :3]
        self.labels = np.fromfile(path.parent.parent / "labels" / f"{path.stem}.label",
                                  dtype=np.uint32)


def features_of(seq, method: GOSMatch, quiet: bool = False) -> tuple[list[dict], float, float]:
    """Feature sets of every scan, with read and compute seconds."""
    out, t_read, t_comp = [], 0.0, 0.0
    objects = getattr(seq, "has_objects", False)
    for i in tqdm(range(len(seq)), desc="gosmatch features", file=sys.stderr, disable=quiet):
        t0 = time.perf_counter()
        scan = seq.scan(i) if objects else _LabelledScan(seq, i)
        t1 = time.perf_counter()
        out.append(method.compute(scan))
        t_read += t1 - t0
        t_comp += time.perf_counter() - t1
    return out, t_read, t_comp


def protocol1_two_stage(method: GOSMatch, db, exclude: int, quiet: bool = True):
    """Protocol 1: retrieve N among ``j <= i - E``, verify, keep the smallest score."""
    n = len(db)
    queries = np.arange(min(exclude, n), n)
    match = np.full(len(queries), -1, dtype=np.int64)
    dist = np.full(len(queries), np.inf)
    poses = np.full((len(queries), 4, 4), np.nan)
    inliers = np.zeros(len(queries), dtype=np.int64)
    k = method.params.candidates
    t0 = time.perf_counter()
    for q, i in enumerate(tqdm(queries, desc="gosmatch p1", file=sys.stderr, disable=quiet)):
        cand, _ = method.retrieve(db, int(i), int(i - exclude + 1), k)
        if len(cand) == 0:
            continue
        ver = method.verify(db, int(i), cand)
        b = int(np.argmin(ver.score))
        if np.isfinite(ver.score[b]):
            match[q], dist[q], poses[q], inliers[q] = cand[b], ver.score[b], ver.pose[b], \
                ver.inliers[b]
    seconds = time.perf_counter() - t0
    yaw = np.full(len(queries), np.nan)
    best = BestMatches(queries, match, dist, yaw, seconds, len(queries) * k, f"candidates:{k}")
    return best, poses, inliers, seconds


def evaluate(seq, method, feats, exclude=30, radius=4.0, quiet=True):
    """Protocol-1 metrics and pose errors of the true matches."""
    db = method.prepare(feats)
    best, poses, _, seconds = protocol1_two_stage(method, db, exclude, quiet)
    positions = seq.positions("camera")
    gt = compute_ground_truth(positions, radius=radius, exclude=exclude, frame="camera")
    res = score_protocol1(best, positions, gt, "revisits", forward=seq.poses[:, :3, 0])
    true = res.is_true
    q, m = best.query[true], best.match[true]
    t_gt = invert_pose(seq.poses[q]) @ seq.poses[m]
    terr = translation_error_m(poses[true], t_gt)
    rerr = rotation_error_deg(poses[true], t_gt)
    metrics = {k: res.metrics[k] for k in ("ap", "f1_max", "r100p", "n_revisits", "n_true_top1")}
    for key in res.metrics:
        if "top1" in key and key != "n_true_top1":
            metrics[key] = res.metrics[key]
    metrics.update(pose_t_median_m=float(np.median(terr)) if len(terr) else None,
                   pose_r_median_deg=float(np.median(rerr)) if len(rerr) else None,
                   match_seconds=seconds)
    return metrics


def object_census(seq, method: GOSMatch, frames) -> dict:
    """Clusters found vs car instances (the simulator's), and objects per class."""
    s = method.cluster_settings
    counts, inst = [], []
    for i in frames:
        scan = _LabelledScan(seq, i)
        _, classes = method.objects(scan)
        counts.append(np.bincount(classes, minlength=3))
        sem = scan.labels & 0xFFFF
        car = sem == 10
        ids, n_pts = np.unique(scan.labels[car] >> 16, return_counts=True)
        cent = [scan.points[car][(scan.labels[car] >> 16) == k].mean(0) for k in ids]
        ok = [c for c, n in zip(cent, n_pts, strict=True)
              if n >= s.min_points and np.linalg.norm(c) < s.max_range]
        inst.append(len(ok))
    counts = np.array(counts)
    return {"vehicles": float(counts[:, 0].mean()), "trunks": float(counts[:, 1].mean()),
            "poles": float(counts[:, 2].mean()), "car_instances": float(np.mean(inst))}


def sweep(args) -> None:
    seq = load_sequence(args.seq, args.poses, args.calib)
    base = get_descriptor("gosmatch", preset=args.preset)
    results = []
    front = [(t, m) for t in args.tolerance for m in args.min_points]
    for tol, mp in front:
        method = GOSMatch(replace(base.params, cluster_tolerance=tol, cluster_min_points=mp),
                          preset=base.preset)
        census = {} if getattr(seq, "has_objects", False) else object_census(
            seq, method, range(0, len(seq), max(1, len(seq) // 20)))
        feats, _, t_comp = features_of(seq, method, quiet=True)
        grid = itertools.product(args.candidates, args.iterations, args.threshold,
                                 args.min_inliers, args.score, args.seeds)
        for n, it, thr, mi, score, seed in grid:
            params = replace(method.params, candidates=n, ransac_iterations=it,
                             inlier_threshold=thr, min_inliers=mi, score=score, seed=seed)
            m = GOSMatch(params, preset=base.preset)
            row = {"tolerance": tol, "min_points": mp, "candidates": n, "iterations": it,
                   "threshold": thr, "min_inliers": mi, "score": score, "seed": seed,
                   **census, "extract_ms": 1e3 * t_comp / len(seq),
                   **evaluate(seq, m, feats, args.exclude, args.radius)}
            results.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))


def census(args) -> None:
    """The ``census`` job (module docstring): objects per scan against what verification needs."""
    from lidar_iris_eval.descriptors.gosmatch.graph import CLASS_NAMES
    from lidar_iris_eval.descriptors.gosmatch.semantics import class_ids, euclidean_clusters

    seq = load_sequence(args.seq, args.poses, args.calib)
    method = get_descriptor("gosmatch", preset=args.preset)
    s = method.cluster_settings
    frames = range(0, len(seq), max(1, args.every))
    labelled, objects, trunk_range, trunk_kept, trunk_total = [], [], [], 0, 0
    for i in frames:
        scan = _LabelledScan(seq, i)
        sem = scan.labels & 0xFFFF
        labelled.append([int(np.isin(sem, ids).sum()) for ids in class_ids(s)])
        objects.append(np.bincount(method.objects(scan)[1], minlength=3)[:3])
        trunk = scan.points[np.isin(sem, class_ids(s)[1])].astype(np.float64)
        trunk_range.append(np.linalg.norm(trunk, axis=1))
        trunk_total += len(trunk)
        trunk_kept += sum(len(c) for c in euclidean_clusters(trunk, s.tolerance, s.min_points))
    labelled, objects = np.array(labelled), np.array(objects)
    per_scan = objects.sum(axis=1)
    ranges = np.concatenate(trunk_range)
    need = method.params.min_inliers
    print(json.dumps({
        "sequence": str(args.seq), "scans": len(frames), "every": args.every,
        "front_end": {"tolerance_m": s.tolerance, "min_points": s.min_points,
                      "max_range_m": s.max_range},
        "labelled_points_per_scan_mean": {n: round(float(labelled[:, k].mean()), 1)
                                          for k, n in enumerate(CLASS_NAMES)},
        "objects_per_scan_mean": {n: round(float(objects[:, k].mean()), 2)
                                  for k, n in enumerate(CLASS_NAMES)},
        "objects_per_scan_median": float(np.median(per_scan)),
        "objects_per_scan_max": int(per_scan.max()),
        "min_inliers": need,
        f"scans_with_at_least_{need}_objects": int((per_scan >= need).sum()),
        "trunk_range_median_m": None if not len(ranges) else round(float(np.median(ranges)), 1),
        "trunk_points_in_kept_clusters": None if not trunk_total
        else round(trunk_kept / trunk_total, 3),
    }, indent=1))


_SHARED: dict = {}


def _match_share(part: int):
    """Protocol-1 matches of every ``processes``-th query (forked worker, shared database)."""
    method, db, exclude, k, processes = (_SHARED[key] for key in
                                         ("method", "db", "exclude", "k", "processes"))
    queries = np.arange(min(exclude, len(db)), len(db))[part::processes]
    match = np.full(len(queries), -1, dtype=np.int64)
    dist = np.full(len(queries), np.inf)
    for q, i in enumerate(queries):
        # as the pipeline: unique candidates sorted by index, NaN never accepted
        cand = np.unique(method.retrieve(db, int(i), int(i - exclude + 1), k)[0])
        if len(cand) == 0:
            continue
        score = method.verify(db, int(i), cand).score
        score = np.where(np.isnan(score), np.inf, score)
        b = int(np.argmin(score))
        if np.isfinite(score[b]):
            match[q], dist[q] = cand[b], score[b]
    return queries, match, dist


def match_processes(method, features, exclude: int, k: int, processes: int):
    """Protocol-1 matches with queries dealt round-robin to forked processes."""
    import multiprocessing as mp

    _SHARED.update(method=method, db=method.prepare(features), exclude=exclude, k=k,
                   processes=processes)
    with mp.get_context("fork").Pool(processes) as pool:
        parts = pool.map(_match_share, range(processes))
    queries = np.concatenate([p[0] for p in parts])
    order = np.argsort(queries)
    return (queries[order], np.concatenate([p[1] for p in parts])[order],
            np.concatenate([p[2] for p in parts])[order])


def speed(args) -> None:
    """Protocol 1 through the pipeline's own path: extract() then two_stage_matches()."""
    from lidar_iris_eval.extract import extract
    from lidar_iris_eval.matching.retrieval import two_stage_matches

    load0 = os.getloadavg()
    seq = load_sequence(args.seq, args.poses, args.calib)
    method = get_descriptor("gosmatch", preset=args.preset)
    # compile the kernels outside the timed region (numba caches them on disk anyway)
    warm = [method.describe(seq.scan(i)) for i in range(2)]
    method.verify(method.prepare(warm), 1, np.array([0]))
    c0, t0 = time.process_time(), time.perf_counter()
    db = extract(seq, method, cache=None, workers=args.workers, progress=not args.quiet)
    c1, t1 = time.process_time(), time.perf_counter()
    k = method.default_candidates()
    best = two_stage_matches(method, db.descriptors, args.exclude, k)
    c2, t2 = time.process_time(), time.perf_counter()
    positions = seq.positions("camera")
    gt = compute_ground_truth(positions, radius=args.radius, exclude=args.exclude, frame="camera")
    res = score_protocol1(best, positions, gt, "revisits", forward=seq.poses[:, :3, 0])
    # the per-pair NumPy reference (geometry.ransac_rigid) on a sample of queries, same run
    features = method.prepare(db.descriptors)
    sample = np.linspace(args.exclude, len(seq) - 1, args.reference_queries).astype(int)
    cand = [method.retrieve(features, int(i), int(i - args.exclude + 1), k)[0] for i in sample]
    r0 = time.perf_counter()
    for i, c in zip(sample, cand, strict=True):
        method.verify(features, int(i), c)
    r1 = time.perf_counter()
    for i, c in zip(sample, cand, strict=True):
        method.verify_reference(features, int(i), c)
    r2 = time.perf_counter()
    parallel = {}
    if args.processes > 1:
        p0, q0 = time.perf_counter(), time.process_time()
        dbp = extract(seq, method, cache=None, workers=args.workers, progress=False)
        p1 = time.perf_counter()
        queries, match, dist = match_processes(method, dbp.descriptors, args.exclude, k,
                                               args.processes)
        p2 = time.perf_counter()
        parallel = {
            "processes": args.processes, "extract_wall_s": p1 - p0, "match_wall_s": p2 - p1,
            "protocol1_wall_s": p2 - p0, "parent_cpu_s": time.process_time() - q0,
            "identical_to_pipeline": bool(np.array_equal(queries, best.query)
                                          and np.array_equal(match, best.match)
                                          and np.array_equal(dist, best.distance)),
        }
    report = {
        "sequence": str(args.seq), "frames": len(seq), "preset": method.preset,
        "params": {f: getattr(method.params, f) for f in method.params.__dataclass_fields__},
        "threads": 1,
        "extract_wall_s": t1 - t0, "extract_cpu_s": c1 - c0,
        "match_wall_s": t2 - t1, "match_cpu_s": c2 - c1,
        "protocol1_wall_s": t2 - t0, "protocol1_cpu_s": c2 - c0,
        "verify_kernel_ms_per_query": 1e3 * (r1 - r0) / len(sample),
        "verify_numpy_reference_ms_per_query": 1e3 * (r2 - r1) / len(sample),
        "kernel_speedup_vs_reference": (r2 - r1) / max(r1 - r0, 1e-12),
        "loadavg_before": load0, "loadavg_after": os.getloadavg(), "cpu_count": os.cpu_count(),
        "metrics": {key: res.metrics[key] for key in ("f1_max", "r100p", "ap", "n_revisits")},
        "parallel": parallel,
    }
    print(json.dumps(report, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="job", required=True)
    for name in ("sweep", "speed", "census"):
        p = sub.add_parser(name)
        p.add_argument("seq")
        p.add_argument("--poses")
        p.add_argument("--calib")
        p.add_argument("--preset", default="reference")
        p.add_argument("--exclude", type=int, default=30)
        p.add_argument("--radius", type=float, default=4.0)
        p.add_argument("--json")
        p.add_argument("-q", "--quiet", action="store_true")
    sp = sub.choices["speed"]
    sp.add_argument("--workers", type=int, default=1, help="extraction processes")
    sp.add_argument("--processes", type=int, default=2,
                    help="also time matching with queries dealt to this many forked processes "
                         "(checked identical to the pipeline's one-process result)")
    sp.add_argument("--reference-queries", type=int, default=40,
                    help="queries timed through the NumPy reference verification")
    sw = sub.choices["sweep"]
    sw.add_argument("--tolerance", type=float, nargs="+", default=[0.5])
    sw.add_argument("--min-points", type=int, nargs="+", default=[10])
    sw.add_argument("--candidates", type=int, nargs="+", default=[10])
    sw.add_argument("--iterations", type=int, nargs="+", default=[100])
    sw.add_argument("--threshold", type=float, nargs="+", default=[1.0])
    sw.add_argument("--min-inliers", type=int, nargs="+", default=[4])
    sw.add_argument("--score", nargs="+", default=["clipped-mean"])
    sw.add_argument("--seeds", type=int, nargs="+", default=[0])
    sub.choices["census"].add_argument("--every", type=int, default=1,
                                       help="every N-th scan")
    args = parser.parse_args(argv)
    {"sweep": sweep, "speed": speed, "census": census}[args.job](args)


if __name__ == "__main__":
    main()
