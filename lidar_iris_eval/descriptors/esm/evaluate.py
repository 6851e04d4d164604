"""ESM's own figures: the real KITTI checks, time per cloud, localizations at zero FP.

Run as ``python -m lidar_iris_eval.descriptors.esm.evaluate kitti DIR`` (DIR holds
``velodyne/``, ``poses.txt`` and ``calib.txt`` of KITTI 00's scans 94, 95, 198, 199)
or ``... zero-fp RUN`` (a ``liris eval`` run folder with protocol 1), or
``... golden VALID.npz [--weights W]`` (CI's golden embeddings from held-out segments),
or ``... auc SEGMENTS.npz --weights A --weights B [--gap 30]`` (segment-retrieval ROC
AUC and accuracy@k of each weights file on held-out segments, side by side; a
``SegmentSet`` file such as ``scripts/train_esm.py``'s ``lm_valid_segments.npz``). Timings are
per-thread CPU time (one core, robust to a shared machine) with BLAS limited to
one thread (``OMP_NUM_THREADS=1``), best of 3 per scan; the figures are printed as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from lidar_iris_eval.descriptors.features import RaggedFeatures

SCANS = (94, 95, 198, 199)


def kitti_report(root: Path, repeats: int = 3) -> dict:
    """Segments, ms per cloud (segmentation / description / matching) and the bar pairs."""
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.io.poses import read_calib, read_kitti_poses
    from lidar_iris_eval.matching.geometry import rotation_error_deg, translation_error_m

    esm = get_descriptor("esm", "single-scan")
    clouds = [np.fromfile(root / "velodyne" / f"{i:06d}.bin", np.float32).reshape(-1, 4)[:, :3]
              for i in SCANS]
    esm.compute(clouds[0])  # warm-up (numba compilation, weight loading)
    seg_ms, desc_ms, feats = [], [], []
    for cloud in clouds:
        best = (np.inf, np.inf)
        for _ in range(repeats):
            esm.timing.update(segmentation=0.0, description=0.0)
            f = esm.compute(cloud)
            best = min(best, (esm.timing["segmentation"], esm.timing["description"]),
                       key=sum)
        seg_ms.append(best[0] * 1e3)
        desc_ms.append(best[1] * 1e3)
        feats.append(f)
    db = esm.prepare(RaggedFeatures.from_list(feats))
    tr = read_calib(root / "calib.txt")
    lidar = np.linalg.inv(tr) @ read_kitti_poses(root / "poses.txt") @ tr
    pairs = {}
    match_ms = []
    for q, c in ((1, 0), (3, 2), (2, 0), (2, 1), (3, 0), (3, 1)):
        db.cache.clear()
        t0 = time.thread_time()
        v = esm.verify(db, q, np.array([c]))
        match_ms.append((time.thread_time() - t0) * 1e3)
        gt = np.linalg.inv(lidar[q]) @ lidar[c]
        ok = np.isfinite(v.score[0])
        pairs[f"{SCANS[q]}-{SCANS[c]}"] = {
            "score": float(v.score[0]) if ok else None, "inliers": int(v.inliers[0]),
            "te_m": float(translation_error_m(v.pose[0], gt)) if ok else None,
            "re_deg": float(rotation_error_deg(v.pose[0], gt)) if ok else None,
        }
    true_scores = [pairs[k]["score"] for k in ("95-94", "199-198")]
    worst_true = max(s if s is not None else np.inf for s in true_scores)
    s198 = pairs["198-94"]["score"]
    return {
        "segments": [len(f["quality"]) for f in feats],
        "ms_segmentation": [round(x, 1) for x in seg_ms],
        "ms_description": [round(x, 1) for x in desc_ms],
        "ms_describe_median": round(float(np.median(np.add(seg_ms, desc_ms))), 1),
        "ms_verify_one_pair_median": round(float(np.median(match_ms)), 2),
        "pairs": pairs,
        "bar_95_94": bool(pairs["95-94"]["score"] is not None and pairs["95-94"]["te_m"] < 0.5
                          and pairs["95-94"]["re_deg"] < 3.0),
        "bar_198_94_worse": bool(s198 is None or s198 > worst_true),
    }


def zero_fp_report(run: Path, name: str = "esm") -> dict:
    """Localizations at zero false positives: accepted true matches before the first false one.

    Protocol 1's matches sorted by score (best first); a false localization is an
    accepted match that is not a true loop (``is_true == 0``).
    """
    import pandas as pd

    m = pd.read_csv(run / "protocol1" / name / "matches.csv")
    m = m[np.isfinite(m["distance"])].sort_values(["distance", "query"], kind="stable")
    false = np.nonzero(m["is_true"].to_numpy() == 0)[0]
    first = int(false[0]) if len(false) else len(m)
    head = m.iloc[:first]
    return {
        "accepted_matches": int(len(m)),
        "localizations_at_zero_fp": int(head["is_true"].sum()),
        "reverse_at_zero_fp": int((head["is_true"] & head["is_reverse"]).sum()),
        "true_matches_total": int(m["is_true"].sum()),
        "reverse_true_total": int((m["is_true"] & m["is_reverse"]).sum()),
        "revisit_queries": int(pd.read_csv(run / "protocol1" / name / "matches.csv")
                               ["is_revisit"].sum()),
    }


def write_golden(valid: Path, out: Path, n: int = 6, weights: str | Path | None = None) -> dict:
    """Golden inputs and outputs of shipped weights for CI (``tests/data/esm*_golden.npz``).

    The inputs are the first ``n`` held-out segments of distinct objects, resampled and
    normalised as at run time; ``weights`` names the file (default ``esm_weights.npz``).
    """
    from lidar_iris_eval.descriptors.esm import network
    from lidar_iris_eval.descriptors.esm.dataset import SegmentSet
    from lidar_iris_eval.descriptors.esm.segmentation import normalise, resample

    path = network.resolve_weights(weights)
    data = SegmentSet.load(valid)
    _, first = np.unique(data.object_id, return_index=True)
    rows = np.sort(first[data.object_id[first] > 0])[:n]
    w, arch = network.load_weights(path)
    pts = np.stack([normalise(resample(data.segment(s), arch.n_points,
                                       np.random.default_rng([0, int(s)])), arch.norm_scale,
                              arch.align_yaw)[0]
                    for s in rows])
    emb = network.embed(w, arch, pts)
    gold = {"points": pts, "embedding": emb, "quality": network.quality(w, emb),
            "sha256": np.array(network.sha256_of(path)), "weights": np.array(path.name)}
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **gold)
    return {"golden": str(out), "weights": path.name, "segments": int(len(rows))}


def auc_report(segments: Path, weights: list, gap: int = 30, n: int = 3000,
               match: float = 2.0) -> dict:
    """Segment-retrieval ROC AUC, its class split and accuracy@k of each weights file.

    ``segments``: a :class:`~lidar_iris_eval.descriptors.esm.dataset.SegmentSet` file
    (held-out segments with object tags); ``gap``: frames two segments of a true pair
    or a scored pair must lie apart (30 = W for local maps, 10 for single scans);
    ``match``: a true pair's world-centroid distance (2 m for simulated object ids, 1 m for
    the centroid tracks of ``scripts/esm_segments.py``).
    """
    from lidar_iris_eval.descriptors.esm import network
    from lidar_iris_eval.descriptors.esm.dataset import SegmentSet
    from lidar_iris_eval.descriptors.esm.metrics import segment_retrieval
    from lidar_iris_eval.errors import LirisError

    try:
        data = SegmentSet.load(segments)
    except (OSError, KeyError, ValueError) as err:
        raise LirisError(str(segments), f"not a segment set ({err})") from None
    out = {"segments": str(segments), "n_segments": len(data), "min_frame_gap": gap,
           "match": match,
           "weights": {}}
    for name in weights or ["esm_weights.npz"]:
        path = network.resolve_weights(name)
        try:
            w, arch = network.load_weights(path)
        except (OSError, KeyError, ValueError) as err:
            raise LirisError(f"--weights {name}", f"cannot read ESM weights ({err})") from None
        m = segment_retrieval(w, arch, data, gap, n, pair_radius=match)
        out["weights"][path.name] = {
            "sha256": network.sha256_of(path)[:16],
            **{k: (round(v, 4) if isinstance(v, float) else v) for k, v in m.items()
               if k != "roc"}}
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["kitti", "zero-fp", "golden", "auc"])
    ap.add_argument("path", type=Path)
    ap.add_argument("--out", type=Path, default=None,
                    help="golden file (default tests/data/esm_golden.npz, or "
                         "esm_localmap_golden.npz for --weights esm_localmap_weights.npz)")
    ap.add_argument("--weights", action="append", default=None,
                    help="weights file (shipped name or path); auc: repeat to compare")
    ap.add_argument("--gap", type=int, default=30, help="auc: minimum frame gap of a pair")
    ap.add_argument("--match", type=float, default=2.0,
                    help="auc: a true pair's world-centroid distance (m; 1 for sequence files)")
    ap.add_argument("--max-segments", type=int, default=3000, help="auc: segments scored")
    args = ap.parse_args(argv)
    if args.what == "golden":
        weights = args.weights[0] if args.weights else None
        default = "esm_golden.npz" if weights in (None, "", "esm_weights.npz") else \
            f"{Path(weights).stem.replace('_weights', '')}_golden.npz"
        out = write_golden(args.path, args.out or Path("tests/data") / default,
                           weights=weights)
    elif args.what == "auc":
        from lidar_iris_eval.errors import LirisError

        try:
            out = auc_report(args.path, args.weights, args.gap, args.max_segments, args.match)
        except LirisError as err:
            print(f"error: {err}", file=sys.stderr)
            raise SystemExit(2) from None
    else:
        out = kitti_report(args.path) if args.what == "kitti" else zero_fp_report(args.path)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
