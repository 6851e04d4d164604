"""Why a segment method does or does not localise on a sequence: the segmentation report.

For any sequence with poses, :func:`segment_report` builds every frame's local
map exactly as ``liris eval -d esm`` does (window ``W`` = E, the sequence's
poses), segments and embeds it with the given ESM descriptor, and measures
with the sequence's poses:

* **segments**: segments per local map and their size (voxels) distribution;
* **repeatability at neighbours**: local map ``i`` against local map
  ``i - gap`` (``gap`` = W by default, so the two maps share no scan): the
  share of map ``i``'s segments inside both crops (``map_radius - 5`` m of
  both poses) that have a segment of the other map whose world centroid lies
  within ``match`` m (1 m);
* **repeatability at revisits**: for every loop query ``i`` (a frame with a
  ground-truth partner ``j <= i - E`` within ``radius`` m), the share of its
  segments that have a segment of ESM's target map (the segments of frames
  ``< i - W + 1`` the target keeps) within ``match`` m;
* **retrieval rank**: for each repeated query segment, the rank (1 = nearest)
  of its true target (the target segment with the nearest world centroid)
  among all target segments by squared-L2 embedding distance; the share
  within ``knn`` (25) is what the consistency search can use;
* **neighbours against the target map**: the same rank for every frame
  ``i >= W`` against the target map of frames ``< i - W + 1`` (the
  place it has just left; on a sequence without revisits the only rank there is);
* **localisation**: what ESM's matcher does on each loop query (localised,
  within ``radius``, best consistent set).

The report is a JSON-ready dict; :func:`report_lines` prints it, and
``lidar_iris_eval.plotting.segment_report`` draws several side by side.
``liris segments`` is the command (it only parses and prints).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from lidar_iris_eval.evaluation.ground_truth import positive_pairs
from lidar_iris_eval.localmaps import local_maps


def extract_local_map_features(seq, esm, limit: int | None = None,
                               progress: Callable[[int, int], None] | None = None) -> list:
    """Every frame's ESM local-map feature set (``compute_local_map``), in order."""
    n = len(seq) if limit is None else min(int(limit), len(seq))
    poses = np.asarray(seq.poses, dtype=np.float64)
    esm.begin_local_maps(0)
    feats = []
    for frame, _ in local_maps(lambda j: np.asarray(seq[j])[:, :3], poses,
                               esm.local_map_settings(), 0, n):
        feats.append(esm.compute_local_map(frame))
        if progress is not None:
            progress(len(feats), n)
    return feats


def neighbour_repeatability(feats: list, poses: np.ndarray, gap: int, match: float,
                            map_radius: float) -> tuple[int, int]:
    """``(repeated, counted)`` over map ``i`` against map ``i - gap`` (module docstring)."""
    rep = cnt = 0
    inner = max(map_radius - 5.0, 1.0)
    for i in range(gap, len(feats)):
        a, b = feats[i]["world"], feats[i - gap]["world"]
        if len(a) == 0 or len(b) == 0:
            continue
        pa, pb = poses[i, :2, 3], poses[i - gap, :2, 3]
        inside = ((np.linalg.norm(a[:, :2] - pa, axis=1) < inner)
                  & (np.linalg.norm(a[:, :2] - pb, axis=1) < inner))
        if not inside.any():
            continue
        d, _ = cKDTree(b).query(a[inside])
        rep += int((d < match).sum())
        cnt += int(inside.sum())
    return rep, cnt


def _median(values) -> float | None:
    values = list(values)
    return float(np.median(values)) if values else None


def _target_rows(esm, db, queries, match: float) -> list[dict]:
    """Per query frame: its segments, those repeated in the target map it is matched
    against (frames ``< i - W + 1``) and the embedding rank of each one's true target."""
    n = len(db)
    rows = []
    for i in queries:
        cut = min(int(i) - esm.window + 1, n)
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
                row["ranks"] = [int(x) for x in 1 + (d2 < true[:, None]).sum(axis=1)]
        rows.append(row)
    return rows


def _summary(rows: list[dict], knn: int) -> dict:
    seg = sum(r["segments"] for r in rows)
    rep = sum(r["repeated"] for r in rows)
    ranks = np.asarray([x for r in rows for x in r["ranks"]], dtype=np.int64)
    return {
        "queries": len(rows),
        "query_segments": int(seg),
        "repeated": int(rep),
        "repeatability": rep / seg if seg else None,
        "target_segments_median": _median(r["target"] for r in rows),
        "rank_median": _median(ranks),
        "within_knn": int((ranks <= knn).sum()),
        "queries_with_6_within_knn": int(sum(
            sum(1 for x in r["ranks"] if x <= knn) >= 6 for r in rows)),
    }


def neighbour_ranks(esm, db, match: float, knn: int) -> dict:
    """Every frame ``i >= W`` against the target map of the frames ``< i - W + 1`` (mostly
    the place it has just left): repeatability and ranks, as at revisits."""
    rows = _target_rows(esm, db, range(esm.window, len(db)), match)
    return {**_summary(rows, knn), "ranks": [x for r in rows for x in r["ranks"]]}


def revisit_report(esm, db, poses: np.ndarray, exclude: int, radius: float, match: float,
                   knn: int) -> dict:
    """Per loop query: segments, repeated segments, ranks of the true targets, localisation."""
    pairs = positive_pairs(poses[:, :3, 3], radius)
    later = pairs[:, 1][pairs[:, 1] - pairs[:, 0] >= exclude] if len(pairs) else []
    rows = _target_rows(esm, db, np.unique(later).astype(int), match)
    for row in rows:
        i = row["query"]
        loc = esm.localisation(db, i, i - exclude + 1)
        row["inliers"] = int(loc.inliers)  # the best consistent set when rejected
        row["frame"] = int(loc.frame)
        row["match_dist_m"] = (float(np.linalg.norm(poses[loc.frame, :3, 3] - poses[i, :3, 3]))
                               if loc.frame >= 0 else None)
    return {
        **_summary(rows, knn),
        "loop_queries": len(rows),
        "localised": sum(r["frame"] >= 0 for r in rows),
        "localised_within_radius": sum(r["frame"] >= 0 and r["match_dist_m"] < radius
                                       for r in rows),
        "best_set_median": _median(r["inliers"] for r in rows),
        "per_query": rows,
    }


def segment_report(seq, esm, exclude: int, *, name: str = "", radius: float = 4.0,
                   match: float = 1.0, gap: int = 0, limit: int | None = None,
                   progress: Callable[[int, int], None] | None = None) -> dict:
    """The segmentation report of ``seq`` (with poses) for the local-map ESM ``esm``.

    ``esm`` is bound to ``exclude`` (its window becomes E unless set); ``gap``
    0 means W. Returns a JSON-ready dict (module docstring for each figure).
    """
    esm = esm.bind_exclusion(int(exclude))
    t0 = time.process_time()
    feats = extract_local_map_features(seq, esm, limit, progress)
    seconds = time.process_time() - t0
    poses = np.asarray(seq.poses, dtype=np.float64)[: len(feats)]
    db = esm.prepare(feats)
    counts = np.diff(db.offsets)
    sizes = (np.concatenate([np.asarray(f["sizes"]) for f in feats]) if feats
             else np.zeros(0, np.int64))
    gap = int(gap) or esm.window
    nrep, ncnt = neighbour_repeatability(feats, poses, gap, match, esm.params.map_radius)
    return {
        "sequence": name, "preset": esm.preset, "exclude": int(exclude), "window": esm.window,
        "params": dataclasses.asdict(esm.params), "frames": len(feats),
        "cpu_s_per_frame": seconds / max(len(feats), 1), "knn": int(esm.params.knn),
        "radius": float(radius), "match": float(match),
        "segments_per_map_median": _median(counts),
        "segments_per_map": [int(c) for c in counts],
        "segment_voxels_pct": (dict(zip(("p10", "p50", "p90"),
                                        np.percentile(sizes, [10, 50, 90]).tolist(), strict=True))
                               if len(sizes) else {}),
        "segment_voxels": [int(s) for s in sizes],
        "neighbours": {"gap": gap, "repeated": nrep, "counted": ncnt,
                       "repeatability": nrep / ncnt if ncnt else None},
        "neighbours_target": neighbour_ranks(esm, db, match, int(esm.params.knn)),
        "revisits": revisit_report(esm, db, poses, int(exclude), radius, match,
                                   int(esm.params.knn)),
    }


def _fmt(value, spec: str = ".3f") -> str:
    return "-" if value is None else format(value, spec)


def report_lines(report: dict) -> list[str]:
    """A few lines of text for one report."""
    rv, nb, k = report["revisits"], report["neighbours"], report["knn"]
    nt = report["neighbours_target"]
    pct = report["segment_voxels_pct"]
    sizes = "/".join(f"{pct[p]:.0f}" for p in ("p10", "p50", "p90")) if pct else "-"
    return [
        f"{report['sequence']}  preset {report['preset']}  E={report['exclude']} "
        f"W={report['window']}",
        f"  {report['frames']} frames, {report['cpu_s_per_frame']:.2f} CPU s/frame; segments per "
        f"map median {_fmt(report['segments_per_map_median'], '.0f')}; voxels per segment "
        f"p10/p50/p90 {sizes}",
        f"  repeatability at neighbours (gap {nb['gap']}): {nb['repeated']}/{nb['counted']} = "
        f"{_fmt(nb['repeatability'])}",
        f"  neighbours against the target map: repeatability {_fmt(nt['repeatability'])}, "
        f"rank median {_fmt(nt['rank_median'], '.0f')} of "
        f"{_fmt(nt['target_segments_median'], '.0f')}; {nt['within_knn']}/{nt['repeated']} "
        f"within k={k}",
        f"  repeatability at revisits: {rv['repeated']}/{rv['query_segments']} = "
        f"{_fmt(rv['repeatability'])} over {rv['loop_queries']} loop queries",
        f"  retrieval rank of the true target: median {_fmt(rv['rank_median'], '.0f')} of "
        f"{_fmt(rv['target_segments_median'], '.0f')} target segments; {rv['within_knn']} "
        f"within k={k}; queries with >= 6 within k: {rv['queries_with_6_within_knn']}",
        f"  localised {rv['localised']} ({rv['localised_within_radius']} within "
        f"{report['radius']:g} m); best consistent set median {_fmt(rv['best_set_median'], '.0f')}",
    ]
