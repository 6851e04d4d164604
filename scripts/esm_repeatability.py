"""Why ESM's local-map pipeline does or does not localise on a sequence (maintainer tool).

For a sequence with poses it builds every frame's local map exactly as
``liris eval -d esm`` does (``window`` = E, the oracle poses), segments it and
embeds the segments, then measures, with the sequence's poses:

* **segments**: segments per local map and their size (voxels) distribution;
* **repeatability at revisits**: for every loop query ``i`` (a frame with a
  ground-truth partner ``j <= i - E`` within ``--radius`` m), the share of its
  segments that have a segment of ESM's target map (the segments of frames
  ``< i - W + 1`` that the target keeps, ``target_lifetimes``) whose world
  centroid lies within ``--match`` m (1 m);
* **repeatability at neighbours**: local map ``i`` against local map
  ``i - gap`` (``gap`` = W by default, so the two maps share no scan), counted
  over the segments of map ``i`` within ``map_radius - 5`` m of both poses;
* **retrieval rank**: for each repeated query segment, the rank (1 = nearest)
  of its true target (the target segment with the nearest world centroid)
  among all target segments by squared-L2 embedding distance; the share ranked
  within ``knn`` (25) is what PROSAC can use.

Prints a summary, writes ``--json`` and (with ``--figure``) a PNG of the
size distribution, the repeatability and the rank histogram.

Example::

    L=../shared/data/real/hku-livox-avia-1
    python scripts/esm_repeatability.py $L/Scans --poses $L/optimized_poses.txt \\
        --lidar-frame-poses --exclude 50 --json /tmp/livox.json
    python scripts/esm_repeatability.py --simulate small-mixed --exclude 30
    python scripts/esm_repeatability.py ... --set min_points=50 --set input_filter=grid
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.evaluation.ground_truth import positive_pairs
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.localmaps import local_maps


def parse_value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def extract(seq, esm, limit: int | None = None):
    """Every frame's ESM local-map features (``compute_local_map``), in order."""
    n = len(seq) if limit is None else min(limit, len(seq))
    poses = np.asarray(seq.poses, dtype=np.float64)
    esm.begin_local_maps(0)
    feats, t0 = [], time.time()
    for frame, _ in local_maps(lambda j: np.asarray(seq[j])[:, :3], poses,
                               esm.local_map_settings(), 0, n):
        feats.append(esm.compute_local_map(frame))
        if len(feats) % 50 == 0:
            print(f"  {len(feats)}/{n} frames, {time.time() - t0:.0f} s", file=sys.stderr)
    return feats


def neighbour_repeatability(feats, poses, gap: int, match: float, map_radius: float):
    """(repeated, counted) over map i vs map i - gap, segments inside both crops."""
    rep = cnt = 0
    inner = max(map_radius - 5.0, 1.0)
    for i in range(gap, len(feats)):
        a, b = feats[i]["world"], feats[i - gap]["world"]
        if len(a) == 0 or len(b) == 0:
            continue
        pa, pb = poses[i, :2, 3], poses[i - gap, :2, 3]
        inside = (np.linalg.norm(a[:, :2] - pa, axis=1) < inner) & \
                 (np.linalg.norm(a[:, :2] - pb, axis=1) < inner)
        if not inside.any():
            continue
        d, _ = cKDTree(b).query(a[inside])
        rep += int((d < match).sum())
        cnt += int(inside.sum())
    return rep, cnt


def revisit_report(esm, db, poses, exclude: int, radius: float, match: float, knn: int):
    """Per loop query: segments, repeated segments, ranks of the true targets."""
    n = len(db)
    pairs = positive_pairs(poses[:, :3, 3], radius)
    later = pairs[:, 1][pairs[:, 1] - pairs[:, 0] >= exclude] if len(pairs) else []
    queries = np.unique(later).astype(int)
    rows, ranks = [], []
    for i in queries:
        cut = min(i - esm.window + 1, n)
        if cut <= 0:
            continue
        t = np.nonzero((db.frame_of < cut) & (db.alive_until >= cut))[0]
        q = db.rows(int(i))
        nq = q.stop - q.start
        row = {"query": int(i), "segments": int(nq), "target": int(len(t)), "repeated": 0,
               "ranks": []}
        if len(t) and nq:
            d, nn = cKDTree(db.world[t]).query(db.world[q])
            ok = np.nonzero(d < match)[0]
            row["repeated"] = int(len(ok))
            if len(ok):
                eq = db.embedding[q][ok].astype(np.float64)
                et = db.embedding[t].astype(np.float64)
                d2 = (eq**2).sum(1)[:, None] + (et**2).sum(1)[None, :] - 2 * eq @ et.T
                true = d2[np.arange(len(ok)), nn[ok]]
                r = 1 + (d2 < true[:, None]).sum(axis=1)
                row["ranks"] = [int(x) for x in r]
                ranks.extend(row["ranks"])
        loc = esm.localisation(db, int(i), int(i) - exclude + 1)
        row["inliers"] = int(loc.inliers)  # the best consistent set when rejected
        row["frame"] = int(loc.frame)
        if loc.frame >= 0:
            row["match_dist_m"] = float(np.linalg.norm(poses[loc.frame, :3, 3] - poses[i, :3, 3]))
        rows.append(row)
    seg = sum(r["segments"] for r in rows)
    rep = sum(r["repeated"] for r in rows)
    ranks = np.asarray(ranks)
    return {
        "loop_queries": len(rows),
        "query_segments": int(seg),
        "repeated": int(rep),
        "repeatability": rep / seg if seg else float("nan"),
        "target_segments_median": float(np.median([r["target"] for r in rows])) if rows
        else float("nan"),
        "rank_median": float(np.median(ranks)) if len(ranks) else float("nan"),
        f"within_knn{knn}": int((ranks <= knn).sum()) if len(ranks) else 0,
        "queries_with_6_within_knn": int(sum(
            sum(1 for x in r["ranks"] if x <= knn) >= 6 for r in rows)),
        "localised": sum(r["frame"] >= 0 for r in rows),
        "localised_within_radius": sum(r["frame"] >= 0 and r["match_dist_m"] < radius
                                       for r in rows),
        "rejected_by_offset": sum(r["frame"] < 0 and r["inliers"] >= esm.params.min_consistent
                                  for r in rows),
        "best_set_median": float(np.median([r["inliers"] for r in rows])) if rows
        else float("nan"),
        "per_query": rows,
    }


def figure(report, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(12, 3.4))
    sizes = np.asarray(report["_sizes"])
    ax[0].hist(np.log10(np.maximum(sizes, 1)), bins=40)
    ax[0].set_xlabel("log10 voxels per segment")
    ax[0].set_title(f"{report['segments_per_map_median']:.0f} segments / map (median)")
    rv = report["revisits"]
    nb = report["neighbours"]
    ax[1].bar(["neighbours", "revisits"], [nb["repeatability"], rv["repeatability"]])
    ax[1].set_ylim(0, 1)
    ax[1].set_title("repeatability (centroid < 1 m)")
    ranks = [x for r in rv["per_query"] for x in r["ranks"]]
    if ranks:
        ax[2].hist(np.log10(ranks), bins=30)
    ax[2].axvline(np.log10(report["knn"]), color="k", ls="--")
    ax[2].set_xlabel("log10 rank of the true target")
    fig.suptitle(report["sequence"])
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", nargs="?")
    ap.add_argument("--poses")
    ap.add_argument("--lidar-frame-poses", action="store_true")
    ap.add_argument("--simulate", help="a simulate preset (e.g. small-mixed) instead of a folder")
    ap.add_argument("--seed", type=int, default=None, help="with --simulate: the world seed")
    ap.add_argument("--exclude", type=int, default=30, help="E (= the local-map window)")
    ap.add_argument("--radius", type=float, default=4.0, help="revisit radius (m)")
    ap.add_argument("--match", type=float, default=1.0, help="centroid match distance (m)")
    ap.add_argument("--gap", type=int, default=0, help="neighbour gap (frames; 0 = W)")
    ap.add_argument("--preset", default="local-maps")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an ESM parameter override (repeatable)")
    ap.add_argument("--limit", type=int, default=None, help="only the first N frames")
    ap.add_argument("--json")
    ap.add_argument("--figure")
    args = ap.parse_args(argv)

    if args.simulate:
        import tempfile

        from lidar_iris_eval.simulate import simulate_sequence

        kw = {"seed": args.seed} if args.seed is not None else {}
        folder = simulate_sequence(Path(tempfile.mkdtemp()) / "seq", preset=args.simulate, **kw)
        seq, name = open_sequence(folder), f"simulate:{args.simulate}"
    else:
        opts = {"lidar_frame": True} if args.lidar_frame_poses else {}
        seq, name = open_sequence(args.sequence, poses=args.poses, **opts), args.sequence
    overrides = dict(kv.split("=", 1) for kv in args.set)
    esm = get_descriptor("esm", args.preset, **{k: parse_value(v) for k, v in overrides.items()})
    esm = esm.bind_exclusion(args.exclude)
    t0 = time.time()
    feats = extract(seq, esm, args.limit)
    seconds = time.time() - t0
    poses = np.asarray(seq.poses, dtype=np.float64)[: len(feats)]
    db = esm.prepare(feats)
    counts = np.diff(db.offsets)
    sizes = np.concatenate([f["sizes"] for f in feats]) if feats else np.zeros(0)
    gap = args.gap or esm.window
    nrep, ncnt = neighbour_repeatability(feats, poses, gap, args.match, esm.params.map_radius)
    report = {
        "sequence": name, "exclude": args.exclude, "window": esm.window, "overrides": overrides,
        "frames": len(feats), "seconds_per_frame": seconds / max(len(feats), 1),
        "knn": esm.params.knn,
        "segments_per_map_median": float(np.median(counts)) if len(counts) else 0.0,
        "segment_voxels_pct": dict(zip(("p10", "p50", "p90"),
                                       np.percentile(sizes, [10, 50, 90]).tolist(), strict=True))
        if len(sizes) else {},
        "neighbours": {"gap": gap, "repeated": nrep, "counted": ncnt,
                       "repeatability": nrep / ncnt if ncnt else float("nan")},
        "revisits": revisit_report(esm, db, poses, args.exclude, args.radius, args.match,
                                   esm.params.knn),
    }
    rv, nb = report["revisits"], report["neighbours"]
    print(f"{name}  E={args.exclude} W={esm.window}  overrides={overrides}")
    print(f"  {report['frames']} frames, {report['seconds_per_frame']:.2f} s/frame; segments per "
          f"map median {report['segments_per_map_median']:.0f}; voxels/segment "
          f"{report['segment_voxels_pct']}")
    print(f"  neighbours (gap {gap}): {nb['repeated']}/{nb['counted']} repeated = "
          f"{nb['repeatability']:.3f}")
    print(f"  revisits: {rv['loop_queries']} loop queries, {rv['repeated']}/{rv['query_segments']}"
          f" query segments repeated = {rv['repeatability']:.3f}; true target rank median "
          f"{rv['rank_median']} (target median {rv['target_segments_median']:.0f} segments), "
          f"{rv['within_knn' + str(report['knn'])]} within k={report['knn']}; queries with >= 6 "
          f"within k: {rv['queries_with_6_within_knn']}")
    print(f"  localise: {rv['localised']} localised ({rv['localised_within_radius']} within "
          f"{args.radius} m), {rv['rejected_by_offset']} rejected by the frame rule only; "
          f"best consistent set median {rv['best_set_median']}")
    if args.figure:
        figure({**report, "_sizes": sizes.tolist()}, Path(args.figure))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
