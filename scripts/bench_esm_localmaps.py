"""ESM on local maps: time per frame split as the paper's Table II, and segment statistics.

    python scripts/bench_esm_localmaps.py time SEQ [--exclude 30] [--every 5]
    python scripts/bench_esm_localmaps.py segments SEQ [SEQ ...] [--json]
        [--kitti ../shared/data/kitti/samples/00]

``time``: for every ``--every``-th frame (after the first E), the CPU time of
this thread (one core) for the local-map update, segmentation, description
(network), matching (k-NN over the target map + centroid consistency) and pose
estimation (consistent sets, rigid fits); prints medians and the 90th
percentile as JSON. ``segments``: segments per single scan and per local map
and their sizes (voxels) on each sequence, and per single scan on real KITTI
scans when given (the shared scans are not consecutive: no local map of them),
side by side as one Markdown table (``--json``: the figures as JSON). Single
scans use SegMap's height rule (z > -1 m), as on real scans without labels.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def _esm(exclude: int):
    from lidar_iris_eval.descriptors import get_descriptor

    return get_descriptor("esm").bind_exclusion(exclude)


def bench_time(seq_path: str, exclude: int, every: int) -> dict:
    from lidar_iris_eval.descriptors.esm import network
    from lidar_iris_eval.descriptors.esm.local_segments import segment_local_map
    from lidar_iris_eval.descriptors.features import RaggedFeatures
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.localmaps import local_maps, odometry_poses

    seq = open_sequence(seq_path)
    esm = _esm(exclude)
    s = esm.local_map_settings()
    poses = odometry_poses(seq, s.odometry)
    w, arch = esm.weights()
    rows, feats = [], []
    for frame, update_s in local_maps(lambda j: seq[j], poses, s, 0, len(seq)):
        t0 = time.thread_time()
        pts, world, sizes = segment_local_map(frame.points, esm.segment_params)
        t1 = time.thread_time()
        emb = network.embed(w, arch, pts)
        q = network.quality(w, emb) if len(emb) else np.zeros(0)
        t2 = time.thread_time()
        inv = np.linalg.inv(frame.pose)
        feats.append({"embedding": emb.astype(np.float32), "quality": q.astype(np.float64),
                      "centroids": world @ inv[:3, :3].T + inv[:3, 3] if len(world)
                      else np.zeros((0, 3)), "world": world, "sizes": sizes,
                      "pose": frame.pose.reshape(1, 4, 4)})
        rows.append([update_s, t1 - t0, t2 - t1])
    db = esm.prepare(RaggedFeatures.from_list(feats))
    out = []
    for i in range(exclude, len(seq), every):
        loc = esm.localisation(db, i, i - exclude + 1)
        out.append([*rows[i], *loc.seconds])
    a = np.asarray(out) * 1e3
    names = ["local_map_update", "segmentation", "description", "matching", "pose_estimation"]
    total = a.sum(1)
    med = np.median(a, 0).round(1).tolist()
    p90 = np.percentile(a, 90, 0).round(1).tolist()
    return {"frames": len(a), "median_ms": dict(zip(names, med, strict=True)),
            "p90_ms": dict(zip(names, p90, strict=True)),
            "total_median_ms": round(float(np.median(total)), 1),
            "total_p90_ms": round(float(np.percentile(total, 90)), 1)}


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
    ap.add_argument("what", choices=["time", "segments"])
    ap.add_argument("sequence", nargs="+", help="sequence folder(s); time: the first only")
    ap.add_argument("--exclude", type=int, default=30)
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--kitti", default=None)
    ap.add_argument("--json", action="store_true", help="segments: JSON instead of the table")
    args = ap.parse_args()
    if args.what == "time":
        print(json.dumps(bench_time(args.sequence[0], args.exclude, args.every), indent=1))
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
