"""Cross-session evaluation: queries from one session against a database from another.

The retrieval benchmarks (PointNetVLAD's Oxford splits, Wild-Places
inter-sequence, HeLiPR, MulRan, OpenPlaceRecognition) evaluate every scan
of a *query* session against every scan of a *database* session recorded on
another day or with another sensor. Rules here:

* **poses** of both sessions are in one world frame, or the query session's
  are moved into the database's frame by a given rigid transform
  (:func:`align_poses`);
* **positives** of query ``q``: database frames closer than the
  convention's radius (strict, or ``<=`` for an inclusive convention), with
  the convention's distance (3-D or planar);
* **no exclusion window**: the database is another session, so every
  database frame is a candidate of every query. (With ``limits`` the same
  code evaluates one sequence against itself under protocol 1's window,
  which is how the ranking metrics of a within-sequence run are computed.)
* **global descriptors** are ranked by descriptor distance over the whole
  database (exact; ties by the smaller database index);
* **two-stage methods** retrieve K candidates from the database and verify
  them; the ranked list is the verified candidates by score (ties by index,
  rejected ones dropped), so a rank beyond the list is unknown
  (:mod:`~lidar_iris_eval.evaluation.ranking`).

Each query's best match (rank 1) also gives a top-1 PR curve, as protocol 1
does within a sequence: the match is accepted when its distance is at most
the threshold and true when it is a positive; recall is over the queries
that have a positive.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.metrics import PRCurve, pr_curve, summarize
from lidar_iris_eval.evaluation.ranking import (
    Ranks,
    ranking_metrics,
    ranks_from_distances,
    ranks_from_lists,
)

#: what metrics.json says about the exclusion window of a cross-session run
EXCLUSION_RULE = ("the exclusion window does not apply across sessions: every database frame "
                  "is a candidate of every query")
TWO_STAGE_RULE = ("two-stage: K retrieval candidates from the database are verified; the ranked "
                  "list is the verified candidates by score (ties by index, rejected dropped)")
GLOBAL_RULE = "global: the whole database ranked by descriptor distance (ties by index)"


def align_poses(poses: np.ndarray, transform: np.ndarray | None) -> np.ndarray:
    """``transform @ poses`` (query world frame -> database world frame); None: unchanged."""
    poses = np.asarray(poses, dtype=np.float64)
    if transform is None:
        return poses
    transform = np.asarray(transform, dtype=np.float64)
    if transform.shape != (4, 4):
        raise LirisError("--align", f"needs a 4x4 transform, got shape {transform.shape}")
    rot = transform[:3, :3]
    if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6) or np.linalg.det(rot) < 0:
        raise LirisError("--align", "the rotation part is not a rotation matrix")
    return transform @ poses


def read_transform(path) -> np.ndarray:
    """A 4x4 rigid transform from a text file: 12 numbers (3x4, row-major) or 16 (4x4)."""
    from pathlib import Path

    path = Path(path)
    try:
        values = np.array(path.read_text().replace(",", " ").split(), dtype=np.float64)
    except OSError as err:
        raise LirisError(path, f"cannot read transform ({err.strerror})") from None
    except ValueError:
        raise LirisError(path, "a transform is 12 or 16 numbers") from None
    if values.size not in (12, 16) or not np.all(np.isfinite(values)):
        raise LirisError(path, f"a transform is 12 or 16 finite numbers, found {values.size}")
    out = np.eye(4)
    out[: values.size // 4] = values.reshape(-1, 4)
    if values.size == 16 and not np.allclose(out[3], [0, 0, 0, 1]):
        raise LirisError(path, "the last row of a 4x4 transform must be 0 0 0 1")
    align_poses(np.eye(4)[None], out)  # checks the rotation
    return out


def cross_positives(query_coords: np.ndarray, db_coords: np.ndarray, radius: float,
                    inclusive: bool = False) -> list[np.ndarray]:
    """Per query, the sorted database indices within ``radius`` (``<`` or ``<=``)."""
    q = np.asarray(query_coords, dtype=np.float64)
    d = np.asarray(db_coords, dtype=np.float64)
    if len(d) == 0:
        return [np.empty(0, np.int64) for _ in range(len(q))]
    lists = cKDTree(d).query_ball_point(q, radius)
    out = []
    for i, idx in enumerate(lists):
        idx = np.asarray(sorted(idx), dtype=np.int64)
        if not inclusive and len(idx):
            dist = np.linalg.norm(d[idx] - q[i], axis=1)
            idx = idx[dist < radius]
        out.append(idx)
    return out


def stack_sessions(database, queries):
    """One descriptor stack: the database session's frames, then the query session's."""
    from lidar_iris_eval.descriptors.features import RaggedFeatures

    database = getattr(database, "descriptors", database)
    queries = getattr(queries, "descriptors", queries)
    if isinstance(database, RaggedFeatures) != isinstance(queries, RaggedFeatures):
        raise LirisError("--query/--database", "the two sessions hold different descriptor kinds")
    if isinstance(database, RaggedFeatures):
        return RaggedFeatures.concatenate([database, queries])
    if np.shape(database)[1:] != np.shape(queries)[1:]:
        raise LirisError("--query/--database",
                         f"descriptor shapes differ: {np.shape(database)[1:]} vs "
                         f"{np.shape(queries)[1:]} (different parameters or sensors?)")
    return np.concatenate([database, queries])


@dataclass(frozen=True)
class CrossSessionResult:
    """Best match, ranks, top-1 PR curve and metrics of a query/database evaluation."""

    match: np.ndarray  # (Q,) database index of the best match, -1 when none
    distance: np.ndarray  # (Q,) its distance (inf when none)
    is_true: np.ndarray  # (Q,) the best match is a positive
    ranks: Ranks
    curve: PRCurve
    metrics: dict


def _positive_block(positives: list[np.ndarray], a: int, b: int, n_db: int) -> np.ndarray:
    block = np.zeros((b - a, n_db), bool)
    for r, q in enumerate(range(a, b)):
        block[r, positives[q]] = True
    return block


class _RankAndBest:
    """Block-pass reducer of a cross-session pass: each query's rank of its first true
    match (Recall@N, MRR) and its best database frame."""

    timed = True

    def __init__(self, positives, limits, n_q: int, n_db: int):
        self.positives, self.limits, self.n_db = positives, limits, n_db
        self.match = np.full(n_q, -1, np.int64)
        self.dist = np.full(n_q, np.inf)
        self.rank = np.zeros(n_q, np.int64)
        self.has = np.zeros(n_q, bool)
        self.size = np.zeros(n_q, np.int64)

    def part(self, rows, d, y):
        a, b = int(rows[0]), int(rows[-1]) + 1
        width = d.shape[1]
        cols = np.arange(width)
        valid = (np.ones((b - a, width), bool) if self.limits is None
                 else cols[None, :] <= self.limits[a:b, None])
        pos = _positive_block(self.positives, a, b, self.n_db)[:, :width]
        r = ranks_from_distances(d, pos, valid)
        masked = np.where(valid & np.isfinite(d), d, np.inf)
        best = np.argmin(masked, axis=1)
        best_d = masked[np.arange(b - a), best]
        return a, b, r, np.where(np.isfinite(best_d), best, -1), best_d

    def merge(self, part) -> None:
        a, b, r, match, dist = part
        self.rank[a:b], self.has[a:b], self.size[a:b] = r.rank, r.has_positive, r.database_size
        self.match[a:b], self.dist[a:b] = match, dist


def _global_pass(descriptor, q_desc, db_desc, positives, limits, rows, progress):
    from lidar_iris_eval.matching.blocks import block_pass

    n_q, n_db = len(q_desc), len(db_desc)
    blocks = []
    for a in range(0, n_q, rows):
        b = min(a + rows, n_q)
        # within a sequence a block only needs the database its last query may see
        width = n_db if limits is None else int(max(limits[a:b].max(), -1)) + 1
        if width == 0:  # no query of the block has a database: rank 0, no match
            if progress is not None:
                progress(b - a)
            continue
        blocks.append((np.arange(a, b), width))
    reducer = _RankAndBest(positives, limits, n_q, n_db)
    block_pass(descriptor, q_desc, blocks, [reducer], progress=progress, database=db_desc)
    size = reducer.size
    return reducer.match, reducer.dist, Ranks(reducer.rank, reducer.has, size, size.copy())


def _two_stage_pass(descriptor, q_desc, db_desc, positives, limits, k, same, progress):
    n_db = len(db_desc)
    stacked = db_desc if same else stack_sessions(db_desc, q_desc)
    prepared = descriptor.prepare(stacked)
    n_q = len(positives)
    match = np.full(n_q, -1, np.int64)
    dist = np.full(n_q, np.inf)
    ranked, scores, sizes, depth = [], [], [], []
    for q in range(n_q):
        index = q if same else n_db + q
        allowed = n_db if limits is None else int(limits[q]) + 1
        cand = np.empty(0, np.int64)
        if allowed > 0:
            found, _ = descriptor.retrieve(prepared, index, allowed, k)
            found = np.asarray(found, dtype=np.int64).reshape(-1)
            cand = np.unique(found[(found >= 0) & (found < allowed)])
        score = np.empty(0)
        if len(cand):
            score = np.asarray(descriptor.verify(prepared, index, cand).score, dtype=np.float64)
            ok = np.isfinite(score)
            if ok.any():
                order = np.lexsort((cand[ok], score[ok]))
                match[q] = cand[ok][order[0]]
                dist[q] = score[ok][order[0]]
        ranked.append(cand)
        scores.append(score)
        sizes.append(max(allowed, 0))
        depth.append(min(k, max(allowed, 0)))
        if progress is not None:
            progress(1)
    pos = [p[p < s] if s else p[:0] for p, s in zip(positives, sizes, strict=True)]
    return match, dist, ranks_from_lists(ranked, pos, sizes, scores, depth)


def evaluate_sessions(
    descriptor: Descriptor,
    query_descriptors,
    database_descriptors,
    positives: list[np.ndarray],
    *,
    limits: np.ndarray | None = None,
    candidates: int | None = None,
    same_sequence: bool = False,
    pair_budget: int = 2_000_000,
    progress: Callable[[int], object] | None = None,
    label: str = "cross-session",
) -> CrossSessionResult:
    """Rank the database for every query and score it (module docstring rules).

    Parameters
    ----------
    descriptor : the method.
    query_descriptors, database_descriptors : stacked descriptors (or
        :class:`~lidar_iris_eval.extract.DescriptorDB`) of the two sessions.
    positives : per query, the database indices that are true matches
        (:func:`cross_positives`).
    limits : optional ``(Q,)`` last database index each query may use (-1:
        none); None is the cross-session rule (the whole database).
    candidates : K of a two-stage method (default ``descriptor.default_candidates()``).
    same_sequence : the query and database are one sequence (indices shared).
    """
    q_desc = getattr(query_descriptors, "descriptors", query_descriptors)
    db_desc = getattr(database_descriptors, "descriptors", database_descriptors)
    n_q, n_db = len(q_desc), len(db_desc)
    if len(positives) != n_q:
        raise LirisError(label, f"{len(positives)} positive lists for {n_q} queries")
    if limits is not None:
        limits = np.asarray(limits, dtype=np.int64)
        if limits.shape != (n_q,):
            raise LirisError(label, f"{len(limits)} database limits for {n_q} queries")
    if descriptor.two_stage:
        k = candidates if candidates is not None else descriptor.default_candidates()
        match, dist, ranks = _two_stage_pass(descriptor, q_desc, db_desc, positives, limits, k,
                                             same_sequence, progress)
        rule = TWO_STAGE_RULE + f" (K = {k})"
    else:
        rows = max(1, pair_budget // max(n_db, 1))
        match, dist, ranks = _global_pass(descriptor, q_desc, db_desc, positives, limits, rows,
                                          progress)
        rule = GLOBAL_RULE
    is_true = np.zeros(n_q, bool)
    for q in np.nonzero(match >= 0)[0]:
        is_true[q] = match[q] in set(positives[q].tolist())
    evaluated = ranks.has_positive
    queries = ranks.database_size > 0
    n_pos = int(np.count_nonzero(evaluated))
    curve = pr_curve(dist[queries], is_true[queries], n_pos)
    metrics = summarize(curve, n_pos, int(np.count_nonzero(queries)), label,
                        "no queries with a database")
    metrics.update(ranking_metrics(ranks))
    metrics.update(
        n_queries=int(np.count_nonzero(queries)),
        n_database=int(n_db),
        n_revisits=n_pos,
        n_true_top1=int(np.count_nonzero(is_true & evaluated)),
        top1_accuracy=(float(np.count_nonzero(is_true & evaluated) / n_pos) if n_pos else None),
        ranking_rule=rule,
    )
    if limits is None:
        metrics["exclusion"] = EXCLUSION_RULE
    return CrossSessionResult(match, dist, is_true, ranks, curve, metrics)
