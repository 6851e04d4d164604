"""ESM's own segment-retrieval metrics (as SegMap and ESM report them).

For held-out segments with known true pairs (:func:`dataset.true_pairs`):

* **ROC** over all segment pairs whose frames are at least ``min_frame_gap``
  apart: true pairs are positives, every other pair a negative, ranked by
  squared L2 embedding distance; AUC by the rank-sum (Mann-Whitney) formula;
* **accuracy@k**: among queries that have at least one true partner, the
  fraction whose ``k`` nearest segments (frames within ``min_frame_gap`` of the
  query excluded, as in loop closure) contain one.

:func:`quality_examples` gives the quality branch's training examples (ESM:
label 1 when a true match is among the segment's k nearest neighbours).
"""

from __future__ import annotations

import numpy as np
from scipy.stats import rankdata


def roc_auc(pos: np.ndarray, neg: np.ndarray) -> float:
    """AUC of "a positive scores lower (closer) than a negative", ties counted half."""
    if len(pos) == 0 or len(neg) == 0:
        return float("nan")
    ranks = rankdata(np.concatenate([-pos, -neg]))
    return float((ranks[: len(pos)].sum() - len(pos) * (len(pos) + 1) / 2) / (len(pos) * len(neg)))


def roc_curve(pos: np.ndarray, neg: np.ndarray, n: int = 101) -> tuple[np.ndarray, np.ndarray]:
    """(FPR, TPR) at ``n`` distance thresholds spanning both samples."""
    thr = np.quantile(np.concatenate([pos, neg]), np.linspace(0, 1, n))
    tpr = np.searchsorted(np.sort(pos), thr, side="right") / max(len(pos), 1)
    fpr = np.searchsorted(np.sort(neg), thr, side="right") / max(len(neg), 1)
    return fpr, tpr


def retrieval_metrics(
    emb: np.ndarray, frame: np.ndarray, pairs: np.ndarray, min_frame_gap: int = 10,
    ks: tuple = (1, 5, 10, 25), world: np.ndarray | None = None,
    coarse: np.ndarray | None = None, ignore: np.ndarray | None = None,
) -> dict:
    """ROC AUC, a coarse ROC and accuracy@k of embeddings ``emb`` (S, d).

    With ``coarse`` (a class per segment) the AUC is also split by negatives:
    ``auc_within_class`` against other objects of the query's class (the hard
    case) and ``auc_cross_class`` against objects of other classes.

    ``ignore`` (a key per segment, e.g. world and object id) marks pairs with the
    same key that are not true pairs as "don't care": they are neither
    negatives of the ROC nor candidates of the k nearest (two views of one car
    from its front and its back, whose centroids lie more than the pair radius
    apart, show the same object but not the same piece).
    """
    n = len(emb)
    world = np.zeros(n, np.int64) if world is None else world
    sq = (emb**2).sum(1)
    d2 = np.maximum(sq[:, None] + sq[None, :] - 2 * emb @ emb.T, 0.0)
    valid = (np.abs(frame[:, None] - frame[None, :]) >= min_frame_gap)
    valid &= world[:, None] == world[None, :]
    truth = np.zeros((n, n), bool)
    truth[pairs[:, 0], pairs[:, 1]] = True
    truth[pairs[:, 1], pairs[:, 0]] = True
    if ignore is not None:
        valid &= truth | (ignore[:, None] != ignore[None, :])
    iu = np.triu_indices(n, 1)
    v = valid[iu]
    pos = d2[iu][v & truth[iu]]
    neg = d2[iu][v & ~truth[iu]]
    fpr, tpr = roc_curve(pos, neg)
    masked = np.where(valid, d2, np.inf)
    order = np.argsort(masked, axis=1)[:, : max(ks)]
    has = truth.any(axis=1)
    hit = np.take_along_axis(truth, order, axis=1)[has]
    acc = {int(k): float(hit[:, :k].any(axis=1).mean()) if has.any() else None for k in ks}
    split = {}
    if coarse is not None:
        same = (coarse[:, None] == coarse[None, :])[iu]
        for name, m in (("auc_within_class", same), ("auc_cross_class", ~same)):
            neg_m = d2[iu][v & ~truth[iu] & m]
            split[name] = roc_auc(pos, neg_m) if len(neg_m) else None
    return {"auc": roc_auc(pos, neg), **split,
            "positives": int(len(pos)), "negatives": int(len(neg)),
            "queries": int(has.sum()), "accuracy_at_k": acc,
            "roc": {"fpr": fpr.round(4).tolist(), "tpr": tpr.round(4).tolist()}}


def segment_retrieval(w: dict, arch, data, min_frame_gap: int = 10, n: int = 3000,
                      seed: int = 0, ignore_same_object: bool = False,
                      pair_radius: float = 2.0) -> dict:
    """:func:`retrieval_metrics` of the NumPy network ``(w, arch)`` on held-out segments.

    ``data`` is a :class:`~lidar_iris_eval.descriptors.esm.dataset.SegmentSet`; at
    most ``n`` of its segments (a seeded uniform subset) are embedded as at run
    time (resampled with the stream ``[0, s]``, normalised) and scored with the
    true pairs of :func:`~lidar_iris_eval.descriptors.esm.dataset.true_pairs` at
    ``min_frame_gap`` (30 = W for local-map segments). ``ignore_same_object``:
    pairs of one object that are not true pairs are "don't care". ``pair_radius``:
    :func:`true_pairs`' (1 m for plain sequences, whose objects are centroid tracks).
    """
    from lidar_iris_eval.descriptors.esm import network
    from lidar_iris_eval.descriptors.esm.dataset import true_pairs
    from lidar_iris_eval.descriptors.esm.segmentation import normalise, resample

    vpairs = true_pairs(data, pair_radius, min_frame_gap=min_frame_gap)
    rows = np.arange(len(data))
    if len(rows) > n:
        rows = np.sort(np.random.default_rng(seed).choice(len(data), n, replace=False))
    emb = network.embed(w, arch, np.stack([
        normalise(resample(data.segment(s), arch.n_points,
                           np.random.default_rng([0, int(s)])), arch.norm_scale,
                  arch.align_yaw)[0]
        for s in rows]))
    remap = -np.ones(len(data), np.int64)
    remap[rows] = np.arange(len(rows))
    keep = (remap[vpairs[:, 0]] >= 0) & (remap[vpairs[:, 1]] >= 0)
    key = data.world_id[rows] * (int(data.object_id.max()) + 1) + data.object_id[rows]
    key = np.where(data.object_id[rows] > 0, key, -1 - np.arange(len(rows)))
    return retrieval_metrics(emb, data.frame[rows], remap[vpairs[keep]],
                             min_frame_gap=min_frame_gap, world=data.world_id[rows],
                             coarse=data.coarse[rows],
                             ignore=key if ignore_same_object else None)


def quality_examples(emb: np.ndarray, frame: np.ndarray, world: np.ndarray, pairs: np.ndarray,
                     k: int = 25, gap: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """The quality branch's examples: ``(rows, labels)`` of the segments that can be matched.

    ESM's quality is "a true match is among the segment's ``k`` nearest
    neighbours" (frames ``>= gap`` apart, same world). A segment with no true
    partner in the sample can never be labelled 1, whatever its shape: it was
    simply not seen again (common on a one-way drive: of 4,000 segments sampled
    from the Riverside keyframes and one simulated world, 3,272 have none in the
    sample). Counting it as a 0 teaches
    the branch which data sets have revisits, not which segments are distinctive,
    so only segments with a partner are examples (``rows``, indices into
    ``emb``); ``labels`` is 1 where a partner is among the ``k`` nearest.

    Parameters
    ----------
    emb : (n, D) array
        Embeddings of the sampled segments.
    frame, world : (n,) int arrays
        Their frames and world (sequence) ids.
    pairs : (m, 2) int array
        True pairs as indices into ``emb``.
    k, gap : int
        Neighbours searched, and the least frame distance of a candidate.
    """
    emb = np.asarray(emb, np.float64)
    n = len(emb)
    partner = [set() for _ in range(n)]
    for a, b in np.asarray(pairs, np.int64).reshape(-1, 2):
        partner[int(a)].add(int(b))
        partner[int(b)].add(int(a))
    rows = np.array([i for i in range(n) if partner[i]], np.int64)
    if len(rows) == 0:
        return rows, np.zeros(0, np.int64)
    sq = (emb**2).sum(1)
    d2 = sq[rows, None] + sq[None, :] - 2.0 * emb[rows] @ emb.T
    bad = (np.abs(frame[rows, None] - frame[None, :]) < gap) | (world[rows, None] != world[None, :])
    d2[bad] = np.inf
    kk = min(k, n)
    near = np.argsort(d2, axis=1, kind="stable")[:, :kk]
    labels = np.array([any(int(j) in partner[int(i)] and np.isfinite(d2[r, j]) for j in near[r])
                       for r, i in enumerate(rows)], dtype=np.int64)
    return rows, labels
