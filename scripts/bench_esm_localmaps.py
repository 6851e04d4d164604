"""ESM on local maps: time per frame split as the paper's Table II, and segment statistics.

    python scripts/bench_esm_localmaps.py time SEQ [--exclude 30] [--every 5] [--describe growth]
    python scripts/bench_esm_localmaps.py check SEQ [--exclude 30] [--every 1]
    python scripts/bench_esm_localmaps.py segments SEQ [SEQ ...] [--json]
        [--kitti ../shared/data/kitti/samples/00]

``time``: for every ``--every``-th frame (after the first E), the CPU time of
this thread (one core) for the local-map update, segmentation (clustering and
id tracking), description (resampling and the network, for the segments the
rule re-describes), matching (k-NN over the target map + centroid
consistency, formed as the consistent sets grow) and pose estimation (rigid
fits); prints medians
and the 90th percentile as JSON, for the rule ``--describe`` (default
``growth``) and the uncached baseline ``--baseline`` (default ``all``) run
frame by frame over the same local maps in the same process (so both see the
same load), their ratio, the cache hit rate, and the 1-minute load average;
and, for the timed rule's queries, the dense consistency matrix that
``localise`` replaced (``reference_localise`` of tests/test_esm_localise.py)
timed query by query next to it: its matching ms, the ratio, and whether
both gave the same localisation (frame, inliers, pose and residual bits).
Run it as ``OMP_NUM_THREADS=1 taskset -c 1 python ...`` for one core.
``check``: for every ``--every``-th query (after the first E), every seed's
consistent set (winning or not) and the localisation against the dense
reference; prints the counts of equal ones as JSON.
``segments``: segments per single scan and per local map
and their sizes (voxels) on each sequence, and per single scan on real KITTI
scans when given (the shared scans are not consecutive: no local map of them),
side by side as one Markdown table (``--json``: the figures as JSON). Single
scans use SegMap's height rule (z > -1 m), as on real scans without labels.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
from pathlib import Path
from unittest import mock

import numpy as np


def _esm(exclude: int, **params):
    from lidar_iris_eval.descriptors import get_descriptor

    esm = get_descriptor("esm").bind_exclusion(exclude)
    if params:
        esm = type(esm)(dataclasses.replace(esm.params, **params), esm.preset)
    return esm


TESTS = Path(__file__).resolve().parents[1] / "tests"


def _reference():
    """tests/test_esm_localise.py: the dense reference (kept there as the oracle)."""
    spec = importlib.util.spec_from_file_location("test_esm_localise",
                                                  TESTS / "test_esm_localise.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _dense_localisation(esm, db, query: int, n_allowed: int, ref):
    """``esm.localisation`` with the dense reference in place of ``localise``."""
    from lidar_iris_eval.descriptors.esm import descriptor

    db.cache.clear()
    with mock.patch.object(descriptor, "localise", ref.reference_localise):
        loc = esm.localisation(db, query, n_allowed)
    db.cache.clear()
    return loc


STAGES = ["local_map_update", "segmentation", "description", "matching", "pose_estimation"]


def _summary(a: np.ndarray) -> dict:
    total = a.sum(1)
    return {"median_ms": dict(zip(STAGES, np.median(a, 0).round(1).tolist(), strict=True)),
            "p90_ms": dict(zip(STAGES, np.percentile(a, 90, 0).round(1).tolist(), strict=True)),
            "total_median_ms": round(float(np.median(total)), 1),
            "total_p90_ms": round(float(np.percentile(total, 90)), 1)}


def bench_time(seq_path: str, exclude: int, every: int, describe: str = "growth",
               baseline: str = "all") -> dict:
    """Both rules over the same local maps, frame by frame (same load), chunked as
    extraction is (tracking restarts every ``DEFAULT_CHUNK_SIZE`` frames)."""
    from lidar_iris_eval.descriptors.features import RaggedFeatures
    from lidar_iris_eval.extract import DEFAULT_CHUNK_SIZE
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.localmaps import local_maps, odometry_poses

    seq = open_sequence(seq_path)
    runs = {"cached": _esm(exclude, describe=describe),
            "baseline": _esm(exclude, describe=baseline)}
    s = runs["cached"].local_map_settings()
    poses = odometry_poses(seq, s.odometry)
    rows = {k: [] for k in runs}
    feats = {k: [] for k in runs}
    load = [os.getloadavg()[0]]
    for frame, update_s in local_maps(lambda j: seq[j], poses, s, 0, len(seq)):
        for name, esm in runs.items():
            if frame.frame % DEFAULT_CHUNK_SIZE == 0:
                esm.begin_local_maps(frame.frame)
            before = dict(esm.timing)
            feats[name].append(esm.compute(frame))
            rows[name].append([update_s, esm.timing["segmentation"] - before["segmentation"],
                               esm.timing["description"] - before["description"]])
        if frame.frame % 50 == 0:
            load.append(os.getloadavg()[0])
    out: dict = {"frames_timed": 0, "describe": describe, "baseline": baseline}
    tables = {}
    ref = _reference()
    dense, equal = [], 0
    for name, esm in runs.items():
        db = esm.prepare(RaggedFeatures.from_list(feats[name]))
        timed = []
        for i in range(exclude, len(seq), every):
            loc = esm.localisation(db, i, i - exclude + 1)
            timed.append([*rows[name][i], *loc.seconds])
            if name == "cached":  # the dense reference on the same query, right after
                old = _dense_localisation(esm, db, i, i - exclude + 1, ref)
                dense.append(old.seconds)
                equal += ref.same_outcome(loc, old)
        tables[name] = np.asarray(timed) * 1e3
        out[name] = _summary(tables[name])
        t = esm.timing
        n = t["described"] + t["reused"]
        out[name]["segments_per_frame"] = round(n / max(1, t["scans"]), 1)
        out[name]["cache_hit_rate"] = round(t["reused"] / n, 3) if n else None
    out["frames_timed"] = len(tables["cached"])
    dense_ms = np.asarray(dense).reshape(-1, 2) * 1e3
    match = tables["cached"][:, 3]
    out["dense_reference"] = {
        "matching_median_ms": round(float(np.median(dense_ms[:, 0])), 1),
        "matching_p90_ms": round(float(np.percentile(dense_ms[:, 0], 90)), 1),
        "pose_estimation_median_ms": round(float(np.median(dense_ms[:, 1])), 1),
        # per query (those that reached the matching: a query without a target takes 0 s)
        "matching_ratio_median": round(float(np.median(
            match[dense_ms[:, 0] > 0] / dense_ms[dense_ms[:, 0] > 0, 0])), 4),
        "matching_ratio_of_medians": round(float(np.median(match) / np.median(dense_ms[:, 0])), 4),
        "same_localisation": f"{equal}/{len(dense_ms)}"}
    ratio = tables["cached"].sum(1) / tables["baseline"].sum(1)
    out["total_ratio_median"] = round(float(np.median(ratio)), 3)
    out["description_ratio_of_medians"] = round(
        float(np.median(tables["cached"][:, 2]) / np.median(tables["baseline"][:, 2])), 3)
    same = [np.array_equal(a["ids"], b["ids"]) for a, b in zip(feats["cached"], feats["baseline"],
                                                              strict=True)]
    out["ids_equal_frames"] = f"{sum(same)}/{len(same)}"
    out["load_average_1min"] = {"min": min(load), "max": max(load)}
    out["omp_num_threads"] = os.environ.get("OMP_NUM_THREADS")
    out["cpu_affinity"] = sorted(os.sched_getaffinity(0))
    return out


def bench_check(seq_path: str, exclude: int, every: int) -> dict:
    """Every seed's consistent set and the localisation, lazy against dense, per query."""
    from lidar_iris_eval.descriptors.esm import target_map
    from lidar_iris_eval.descriptors.features import RaggedFeatures
    from lidar_iris_eval.extract import DEFAULT_CHUNK_SIZE
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.localmaps import local_maps, odometry_poses

    seq = open_sequence(seq_path)
    esm = _esm(exclude)
    s = esm.local_map_settings()
    feats = []
    for frame, _ in local_maps(lambda j: seq[j], odometry_poses(seq, s.odometry), s, 0,
                               len(seq)):
        if frame.frame % DEFAULT_CHUNK_SIZE == 0:
            esm.begin_local_maps(frame.frame)
        feats.append(esm.compute(frame))
    db = esm.prepare(RaggedFeatures.from_list(feats))
    ref = _reference()
    lazy = target_map._consistent_sets
    counts = {"queries": 0, "same_localisation": 0, "calls": 0, "same_sets": 0, "seeds": 0,
              "sets": 0, "correspondences_max": 0}

    def both(qa, tb, t_world, q_cent, threshold, min_consistent, seeds, grow="order"):
        new = lazy(qa, tb, t_world, q_cent, threshold, min_consistent, seeds, grow)
        old = ref.reference_sets(qa, tb, t_world, q_cent, threshold, min_consistent, seeds,
                                 grow)
        counts["calls"] += 1
        counts["same_sets"] += ref.same_sets(new, old)
        counts["seeds"] += seeds
        counts["sets"] += len(old)
        counts["correspondences_max"] = max(counts["correspondences_max"], len(qa))
        return new

    for i in range(exclude, len(seq), every):
        db.cache.clear()
        with mock.patch.object(target_map, "_consistent_sets", both):
            loc = esm.localisation(db, i, i - exclude + 1)
        old = _dense_localisation(esm, db, i, i - exclude + 1, ref)
        counts["queries"] += 1
        counts["same_localisation"] += ref.same_outcome(loc, old)
    return counts


def _sizes_summary(counts, sizes) -> dict:
    sizes = np.asarray(sizes)
    return {"per_cloud_median": float(np.median(counts)) if len(counts) else None,
            "per_cloud_range": [int(np.min(counts)), int(np.max(counts))] if len(counts) else None,
            "size_quartiles": np.percentile(sizes, [25, 50, 75]).round(0).tolist()
            if len(sizes) else None, "segments": int(len(sizes))}


def _local_map_segments(esm, seq, exclude: int, every: int) -> dict:
    """Segments per local map (frames >= E, every ``every``-th) and their sizes."""
    from lidar_iris_eval.descriptors.esm.local_segments import segment_local_map
    from lidar_iris_eval.localmaps import local_maps, odometry_poses

    s = esm.local_map_settings()
    poses = odometry_poses(seq, s.odometry)
    counts, sizes = [], []
    for frame, _ in local_maps(lambda j: seq[j], poses, s, 0, len(seq)):
        if frame.frame % every or frame.frame < exclude:
            continue
        _, _, sz = segment_local_map(frame.points, esm.segment_params)
        counts.append(len(sz))
        sizes.extend(sz.tolist())
    return _sizes_summary(counts, sizes)


def segments_table(results: dict[str, dict], kitti: str | None) -> str:
    """One Markdown table of :func:`bench_segments` results, real scans first."""
    lines = ["| | segments per cloud (median, range) | size in voxels (quartiles) |",
             "|---|---|---|"]

    def row(name: str, r: dict) -> str:
        if r["per_cloud_median"] is None:
            return f"| {name} | n/a | n/a |"
        lo, hi = r["per_cloud_range"]
        q = " / ".join(f"{v:.0f}" for v in r["size_quartiles"]) if r["size_quartiles"] else "n/a"
        return f"| {name} | {r['per_cloud_median']:g} ({lo}–{hi}) | {q} |"

    if kitti:
        first = next(iter(results.values()))
        lines.append(row(f"real KITTI single scans (`{kitti}`)", first["kitti_single_scan"]))
    for seq, r in results.items():
        lines.append(row(f"simulated single scans (`{seq}`)", r["simulated_single_scan"]))
    for seq, r in results.items():
        lines.append(row(f"simulated local maps (`{seq}`)", r["simulated_local_map"]))
    return "\n".join(lines)


def bench_segments(seq_path: str, exclude: int, kitti: str | None, every: int) -> dict:
    """Segment statistics of one sequence (single scans, local maps) and of real scans."""
    from lidar_iris_eval.descriptors.esm.segmentation import segment_scan
    from lidar_iris_eval.io import open_sequence

    esm = _esm(exclude)
    sp = esm.segment_params
    seq = open_sequence(seq_path)
    counts, sizes = [], []
    for i in range(0, len(seq), every):
        segs = segment_scan(seq[i], None, sp)  # height rule, as on real scans
        counts.append(len(segs))
        sizes.extend(segs.sizes.tolist())
    out = {"simulated_single_scan": _sizes_summary(counts, sizes),
           "simulated_local_map": _local_map_segments(esm, seq, exclude, every)}
    if kitti:
        from pathlib import Path

        from lidar_iris_eval.io.scans import read_kitti_bin

        counts, sizes = [], []
        for path in sorted(Path(kitti, "velodyne").glob("*.bin")):
            segs = segment_scan(read_kitti_bin(path).points, None, sp)
            counts.append(len(segs))
            sizes.extend(segs.sizes.tolist())
        out["kitti_single_scan"] = _sizes_summary(counts, sizes)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["time", "segments", "check"])
    ap.add_argument("sequence", nargs="+", help="sequence folder(s); time: the first only")
    ap.add_argument("--exclude", type=int, default=30)
    ap.add_argument("--every", type=int, default=None,
                    help="every n-th frame (default: 5; check: 1)")
    ap.add_argument("--kitti", default=None)
    ap.add_argument("--describe", default="growth", help="time: the rule timed (esm.describe)")
    ap.add_argument("--baseline", default="all", help="time: the rule it is compared with")
    ap.add_argument("--json", action="store_true", help="segments: JSON instead of the table")
    args = ap.parse_args()
    if args.every is None:
        args.every = 1 if args.what == "check" else 5
    if args.what == "check":
        print(json.dumps(bench_check(args.sequence[0], args.exclude, args.every), indent=1))
        return
    if args.what == "time":
        print(json.dumps(bench_time(args.sequence[0], args.exclude, args.every, args.describe,
                                    args.baseline), indent=1))
        return
    results = {}
    for k, seq in enumerate(args.sequence):  # real scans once, with the first sequence
        results[seq] = bench_segments(seq, args.exclude, args.kitti if k == 0 else None,
                                      args.every)
    if args.json:
        print(json.dumps(results, indent=1))
    else:
        print(segments_table(results, args.kitti))


if __name__ == "__main__":
    main()
