"""Ranking metrics of place recognition: Recall@N (N = 1..25), Recall@1 %, MRR.

The retrieval papers since PointNetVLAD score a query by where its first true
match falls in the database ranked by descriptor distance. This module turns
a distance block, or per-query ranked candidate lists, into that rank and
the summary numbers. It serves within-sequence runs (the database of query
``i`` is what protocol 1 allows, frames ``j <= limit[i]``) and cross-session
runs (the database is the other session, no exclusion window).

Definitions (written to ``metrics.json`` as :data:`RANKING_DEFINITION`)
----------------------------------------------------------------------
* **evaluated queries** – queries with at least one positive (a database
  frame within the convention's radius) in their database; the others
  cannot be right or wrong and are left out of every ranking number (as in
  PointNetVLAD's and Wild-Places' ``get_recall``: ``len(true_neighbours) ==
  0`` -> ``continue``).
* **rank** – database frames are ordered by distance, ties by the smaller
  frame index (the tie rule of protocol 1's best match, so Recall@1 is
  exactly protocol 1's top-1 accuracy over revisit queries). The rank of a
  query is the 1-based position of its first positive. Non-finite
  distances (a rejected pair) are never ranked.
* **Recall@N** – share of evaluated queries whose rank is ``<= N``.
* **Recall@1 %** – Recall@N with ``N = max(round(D / 100), 1)``, ``D`` the
  database size (PointNetVLAD's ``threshold``). Within one sequence the
  database grows with the query, so ``N`` is computed per query from its own
  database size (``limit[i] + 1`` frames); a cross-session run has one ``D``.
  Python's ``round`` (half to even) is used, like the peers' code.
* **MRR** – mean over evaluated queries of ``1 / rank``, a query whose
  positives are not ranked at all counting 0. Wild-Places' ``mrr`` is the
  mean of ``1 / rank`` over the queries found within the top 25 only
  (``recall_idx``), which is reported beside it as ``mrr_top25_found``.
* **ranked lists** – a two-stage method ranks only its K retrieval
  candidates per query (verified; a rejected one is a known miss), so a
  rank beyond K is unknown: Recall@N for ``N > K`` is undefined (``null``,
  never 0) as soon as one query's positives are not among its candidates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: Recall@N is reported for N = 1 .. MAX_N
MAX_N = 25

RANKING_DEFINITION = (
    "evaluated queries: those with a positive in their database; rank: 1-based position of "
    "the first positive with the database ordered by distance, ties by the smaller frame "
    "index, non-finite distances never ranked; Recall@N: share of evaluated queries with rank "
    "<= N; Recall@1%: N = max(round(D/100), 1) with D the query's database size; MRR: mean "
    "1/rank, 0 when no positive is ranked; mrr_top25_found: Wild-Places' MRR (mean 1/rank "
    "over queries found in the top 25)"
)


@dataclass(frozen=True)
class Ranks:
    """Per-query rank of the first positive.

    Attributes
    ----------
    rank : ``(Q,)`` int64, 1-based rank of the first positive; 0 when none of
        the query's positives is ranked (beyond a candidate list, or only
        non-finite distances).
    has_positive : ``(Q,)`` bool, the query has a positive in its database
        (only these are evaluated).
    database_size : ``(Q,)`` int64, frames in each query's database.
    ranked : ``(Q,)`` int64, how many database frames each query's ranking
        covers (the database size for an exhaustive search, K or fewer for
        a candidate list).
    """

    rank: np.ndarray
    has_positive: np.ndarray
    database_size: np.ndarray
    ranked: np.ndarray

    def __len__(self) -> int:
        return len(self.rank)


def one_percent_n(database_size: np.ndarray | int) -> np.ndarray:
    """``max(round(D / 100), 1)`` per database size (Python's half-to-even round)."""
    sizes = np.atleast_1d(np.asarray(database_size, dtype=np.int64))
    return np.maximum(np.array([round(int(d) / 100) for d in sizes], dtype=np.int64), 1)


def ranks_from_distances(
    distances: np.ndarray,
    positive: np.ndarray,
    valid: np.ndarray | None = None,
) -> Ranks:
    """Exact ranks from a dense ``(Q, D)`` distance block.

    Parameters
    ----------
    distances : ``(Q, D)`` descriptor distances, query rows, database columns
        (column index = database frame index, which breaks ties).
    positive : ``(Q, D)`` bool, the pair is a true match.
    valid : ``(Q, D)`` bool or None; False entries are not in the query's
        database (the exclusion window). None: every entry is.
    """
    d = np.asarray(distances, dtype=np.float64)
    pos = np.asarray(positive, dtype=bool)
    if d.ndim != 2 or pos.shape != d.shape:
        raise ValueError("distances and positive must be (Q, D) arrays of the same shape")
    ok = np.ones(d.shape, bool) if valid is None else np.asarray(valid, dtype=bool)
    if ok.shape != d.shape:
        raise ValueError("valid must have the shape of distances")
    pos = pos & ok
    has_positive = pos.any(axis=1)
    database_size = ok.sum(axis=1).astype(np.int64)
    finite = ok & np.isfinite(d)
    q, n_db = d.shape
    rank = np.zeros(q, np.int64)
    cols = np.arange(n_db)
    for i in np.nonzero(has_positive)[0]:
        cand = pos[i] & finite[i]
        if not cand.any():
            continue
        dp = d[i, cand]
        jp = cols[cand]
        best = np.lexsort((jp, dp))[0]  # smallest distance, then smallest index
        d_star, j_star = dp[best], jp[best]
        row, fin = d[i], finite[i]
        better = fin & ((row < d_star) | ((row == d_star) & (cols < j_star)))
        rank[i] = int(np.count_nonzero(better)) + 1
    # an exhaustive search ranks its whole database (a non-finite distance is "never")
    return Ranks(rank, has_positive, database_size, database_size.copy())


def ranks_from_lists(
    ranked: Sequence[np.ndarray],
    positives: Sequence[np.ndarray] | Sequence[set],
    database_size: np.ndarray | Sequence[int],
    scores: Sequence[np.ndarray] | None = None,
    depth: np.ndarray | Sequence[int] | None = None,
) -> Ranks:
    """Ranks from per-query candidate lists (two-stage methods, a k-d tree's top K).

    Parameters
    ----------
    ranked : per query, database frame indices. With ``scores`` they are
        sorted here by (score, index) and non-finite scores dropped (a
        rejected candidate); without, they are taken as already ranked.
    positives : per query, the database frames that are true matches (all of
        them, retrieved or not: a query without any is not evaluated).
    database_size : per query, the size of its database.
    scores : optional per-query scores (distances) aligned with ``ranked``.
    depth : per query, how deep the list looked (K of a retrieval, at most
        the database size): a candidate rejected by verification is a known
        miss, a frame beyond K is not. Default: the length of each list.
    """
    n = len(ranked)
    if len(positives) != n or len(database_size) != n:
        raise ValueError("ranked, positives and database_size need one entry per query")
    rank = np.zeros(n, np.int64)
    covered = np.zeros(n, np.int64)
    has_positive = np.zeros(n, bool)
    for i in range(n):
        cand = np.asarray(ranked[i], dtype=np.int64).reshape(-1)
        if scores is not None:
            s = np.asarray(scores[i], dtype=np.float64).reshape(-1)
            if s.shape != cand.shape:
                raise ValueError(f"query {i}: {len(s)} scores for {len(cand)} candidates")
            keep = np.isfinite(s)
            cand, s = cand[keep], s[keep]
            cand = cand[np.lexsort((cand, s))]
        covered[i] = len(cand) if depth is None else int(depth[i])
        pos = np.asarray(sorted(positives[i]), dtype=np.int64)
        has_positive[i] = len(pos) > 0
        if not len(pos) or not len(cand):
            continue
        hit = np.nonzero(np.isin(cand, pos))[0]
        if len(hit):
            rank[i] = int(hit[0]) + 1
    return Ranks(rank, has_positive, np.asarray(database_size, dtype=np.int64), covered)


def ranking_metrics(ranks: Ranks, max_n: int = MAX_N) -> dict:
    """Recall@1..``max_n``, Recall@1 %, MRR and counts as a JSON-ready dict.

    Undefined values are None: every number when no query is evaluated;
    Recall@N (and Recall@1 %) where some evaluated query's ranking stops
    before N without having found a positive.
    """
    ev = ranks.has_positive
    n_eval = int(np.count_nonzero(ev))
    out = {
        "n_ranking_queries": n_eval,
        "recall_at_n": [None] * max_n,
        "recall_at_1": None,
        "recall_at_1pct": None,
        "recall_1pct_n": None,
        "mrr": None,
        "mrr_top25_found": None,
        "ranking_definition": RANKING_DEFINITION,
    }
    if n_eval == 0:
        return out
    rank = ranks.rank[ev]
    found = rank > 0
    # a query not found in a list shorter than its database has an unknown rank beyond it
    unknown_after = np.where(~found & (ranks.ranked[ev] < ranks.database_size[ev]),
                             ranks.ranked[ev], np.iinfo(np.int64).max)
    recall = []
    for n in range(1, max_n + 1):
        if np.any(unknown_after < n):
            recall.append(None)
        else:
            recall.append(float(np.count_nonzero(found & (rank <= n)) / n_eval))
    n1 = one_percent_n(ranks.database_size[ev])
    r1p = None if np.any(unknown_after < n1) else float(
        np.count_nonzero(found & (rank <= n1)) / n_eval)
    sizes = np.unique(n1)
    reciprocal = np.where(found, 1.0 / np.maximum(rank, 1), 0.0)
    top = found & (rank <= MAX_N)
    out.update(
        recall_at_n=recall,
        recall_at_1=recall[0],
        recall_at_1pct=r1p,
        recall_1pct_n=int(sizes[0]) if len(sizes) == 1 else f"{int(sizes[0])}..{int(sizes[-1])}",
        mrr=float(np.mean(reciprocal)),
        mrr_top25_found=float(np.mean(reciprocal[top])) if top.any() else None,
    )
    return out


def within_sequence_valid(limits: np.ndarray, n_database: int | None = None) -> np.ndarray:
    """``(Q, D)`` bool: database frame ``j`` is allowed for query ``i`` (``j <= limits[i]``)."""
    limits = np.asarray(limits, dtype=np.int64)
    n_database = len(limits) if n_database is None else n_database
    return np.arange(n_database)[None, :] <= limits[:, None]
