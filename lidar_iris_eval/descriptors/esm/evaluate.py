"""ESM's own figures: the real KITTI checks, time per cloud, localizations at zero FP.

Run as ``python -m lidar_iris_eval.descriptors.esm.evaluate kitti DIR`` (DIR holds
``velodyne/``, ``poses.txt`` and ``calib.txt`` of KITTI 00's scans 94, 95, 198, 199)
or ``... zero-fp RUN`` (a ``liris eval`` run folder with protocol 1), or
``... golden VALID.npz`` (CI's golden embeddings from held-out segments). Timings are
per-thread CPU time (one core, robust to a shared machine) with BLAS limited to
one thread (``OMP_NUM_THREADS=1``), best of 3 per scan; the figures are printed as JSON.
"""

from __future__ import annotations

import argparse
import json
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


def write_golden(valid: Path, out: Path, n: int = 6) -> dict:
    """Golden inputs and outputs of the shipped weights for CI (``tests/data/esm_golden.npz``).

    The inputs are the first ``n`` held-out segments of distinct objects, resampled and
    normalised as at run time.
    """
    from lidar_iris_eval.descriptors.esm import network
    from lidar_iris_eval.descriptors.esm.dataset import SegmentSet
    from lidar_iris_eval.descriptors.esm.segmentation import normalise, resample

    data = SegmentSet.load(valid)
    _, first = np.unique(data.object_id, return_index=True)
    rows = np.sort(first[data.object_id[first] > 0])[:n]
    w, arch = network.load_weights()
    pts = np.stack([normalise(resample(data.segment(s), arch.n_points,
                                       np.random.default_rng([0, int(s)])), arch.norm_scale,
                              arch.align_yaw)[0]
                    for s in rows])
    emb = network.embed(w, arch, pts)
    gold = {"points": pts, "embedding": emb, "quality": network.quality(w, emb),
            "sha256": np.array(network.sha256_of(network.WEIGHTS_FILE))}
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez(out, **gold)
    return {"golden": str(out), "segments": int(len(rows))}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=["kitti", "zero-fp", "golden"])
    ap.add_argument("path", type=Path)
    ap.add_argument("--out", type=Path, default=Path("tests/data/esm_golden.npz"))
    args = ap.parse_args(argv)
    if args.what == "golden":
        out = write_golden(args.path, args.out)
    else:
        out = kitti_report(args.path) if args.what == "kitti" else zero_fp_report(args.path)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
