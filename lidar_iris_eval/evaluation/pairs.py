"""Pair-list protocol: a PR curve over a given list of (query, database, label) pairs.

SSC (lilin-hitcrt/SSC) scores place recognition on lists of pairs instead of
every query or every pair: ``script/gen_pairs.py`` takes the KITTI camera
poses' ground-plane coordinates (pose columns 3 and 11, camera x and z), a
pair ``(i, j)`` is positive when closer than 3 m with ``i - j > 50``, negative
when farther than 20 m with ``i > j``; the lists shipped in ``pairs/neg_N/``
(``"%06d %06d label"`` per line, label 1 or 0) hold every positive and N
times as many negatives drawn from the candidates. SSC's code does not state
the sampling seed, so :func:`ssc_pairs` states its own (``seed``, NumPy
``default_rng``, negatives drawn uniformly without replacement).

``liris eval --pairs FILE`` scores a user's list: each pair's distance is
the method's verification score of database frame ``j`` for query ``i``
(for a global descriptor, the descriptor distance), a pair is accepted when
its distance is at most the threshold, and the curve is the exact PR curve
of :func:`~lidar_iris_eval.evaluation.metrics.pr_curve` with the positives
of the list as denominator. There is no exclusion window: the list says
which pairs count.

File format (read by :func:`read_pairs`): one pair a line, ``i j label``
separated by spaces or commas, ``i`` and ``j`` frame indices (0-based),
``label`` 1 (same place) or 0; blank lines and lines starting with ``#`` are
ignored.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.ground_truth import gt_coordinates
from lidar_iris_eval.evaluation.metrics import PRCurve, pr_curve, summarize


@dataclass(frozen=True)
class SSCRule:
    """SSC's pair-list rule (``script/gen_pairs.py``), with the sampling made explicit."""

    positive_radius: float = 3.0
    min_gap: int = 50  # positives need i - j > min_gap
    negative_radius: float = 20.0
    negative_ratio: int = 10  # negatives per positive (SSC ships x1, x10, x20, x50, x100)
    seed: int = 0
    distance: str = "planar"
    pose_frame: str = "camera"
    source: str = ("lilin-hitcrt/SSC script/gen_pairs.py (pose columns 3 and 11, dis < 3 with "
                   "i - j > 50, dis > 20 with i > j) and pairs/neg_N/*.txt (N negatives per "
                   "positive); sampling seed stated by liris")


def ssc_pairs(positions: np.ndarray, rule: SSCRule = SSCRule(), block: int = 512) -> np.ndarray:
    """``(P, 3)`` int64 rows ``(i, j, label)``, ``i > j``: every positive, then the sampled
    negatives, each group sorted by ``(i, j)``.

    ``positions`` are ``(N, 3)`` translations in ``rule.pose_frame``. Negatives are
    ``min(ratio * positives, all negatives)`` drawn without replacement.
    """
    coords = gt_coordinates(positions, rule.pose_frame, rule.distance)
    n = len(coords)
    pos_rows, counts = [], np.zeros(n, np.int64)
    for a in range(0, n, block):
        b = min(a + block, n)
        d = np.linalg.norm(coords[a:b, None] - coords[None, :b], axis=2)
        i = np.arange(a, b)[:, None]
        j = np.arange(b)[None, :]
        lower = j < i
        pi, pj = np.nonzero(lower & (d < rule.positive_radius) & (i - j > rule.min_gap))
        pos_rows.append(np.stack([pi + a, pj], 1))
        counts[a:b] = np.count_nonzero(lower & (d > rule.negative_radius), axis=1)
    positives = np.concatenate(pos_rows) if pos_rows else np.empty((0, 2), np.int64)
    total = int(counts.sum())
    want = min(rule.negative_ratio * len(positives), total)
    rng = np.random.default_rng(rule.seed)
    chosen = np.sort(rng.choice(total, size=want, replace=False)) if want else \
        np.empty(0, np.int64)
    # decode the k-th negative (in row-major order of i, then j) back to its pair
    starts = np.concatenate([[0], np.cumsum(counts)])
    neg = np.empty((want, 2), np.int64)
    rows = np.searchsorted(starts, chosen, side="right") - 1
    for i in np.unique(rows):
        sel = rows == i
        d = np.linalg.norm(coords[i] - coords[:i], axis=1)
        cols = np.nonzero(d > rule.negative_radius)[0]
        neg[sel, 0] = i
        neg[sel, 1] = cols[chosen[sel] - starts[i]]
    out = np.concatenate([np.column_stack([positives, np.ones(len(positives), np.int64)]),
                          np.column_stack([neg, np.zeros(len(neg), np.int64)])])
    return out.astype(np.int64)


def pairs_text(pairs: np.ndarray) -> str:
    """The SSC file format, ``%06d %06d label`` per line."""
    return "".join(f"{i:06d} {j:06d} {lab}\n" for i, j, lab in np.asarray(pairs).tolist())


def write_pairs(path: str | os.PathLike, pairs: np.ndarray) -> None:
    """Write a pair list atomically (temporary file + :func:`os.replace`)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_text(pairs_text(pairs))
    os.replace(tmp, path)


def read_pairs(path: str | os.PathLike, n_query: int, n_database: int | None = None
               ) -> np.ndarray:
    """Read a pair list (module docstring format) as ``(P, 3)`` int64 ``(i, j, label)``.

    Every bad line is a :class:`LirisError` naming the file and line.
    """
    path = Path(path)
    n_database = n_query if n_database is None else n_database
    try:
        text = path.read_text()
    except OSError as err:
        raise LirisError(path, f"cannot read pair list ({err.strerror})") from None
    except UnicodeDecodeError:
        raise LirisError(path, "not a text file") from None
    rows = []
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        where = f"{path}:{number}"
        if len(parts) != 3:
            raise LirisError(where, f"expected 'i j label', found {len(parts)} fields")
        try:
            i, j, label = (int(p) for p in parts)
        except ValueError:
            raise LirisError(where, "frame indices and label must be integers") from None
        if label not in (0, 1):
            raise LirisError(where, f"label must be 0 or 1, got {label}")
        if not 0 <= i < n_query or not 0 <= j < n_database:
            raise LirisError(where, f"frame index out of range (query frames 0..{n_query - 1}, "
                                    f"database frames 0..{n_database - 1})")
        if n_database == n_query and i == j:
            raise LirisError(where, "a frame paired with itself")
        rows.append((i, j, label))
    if not rows:
        raise LirisError(path, "no pairs")
    return np.asarray(rows, dtype=np.int64)


def pair_distances_of(descriptor, db, pairs: np.ndarray) -> np.ndarray:
    """``(P,)`` verification score of each pair (``descriptor.verify`` grouped by query).

    ``db`` is what ``descriptor.prepare`` returned for the frames the indices
    refer to. Non-finite scores (rejected) are never accepted.
    """
    pairs = np.asarray(pairs, dtype=np.int64)
    out = np.full(len(pairs), np.nan)
    for i in np.unique(pairs[:, 0]):
        sel = np.nonzero(pairs[:, 0] == i)[0]
        cand, inverse = np.unique(pairs[sel, 1], return_inverse=True)
        result = descriptor.verify(db, int(i), cand)
        out[sel] = np.asarray(result.score, dtype=np.float64)[inverse]
    return out


@dataclass(frozen=True)
class PairListResult:
    """Distances, exact PR curve and metrics of a pair list."""

    pairs: np.ndarray
    distance: np.ndarray
    curve: PRCurve
    metrics: dict


def score_pair_list(pairs: np.ndarray, distances: np.ndarray, source: str = "pair list"
                    ) -> PairListResult:
    """PR over a pair list: accepted when ``distance <= tau``, denominator = its positives."""
    pairs = np.asarray(pairs, dtype=np.int64)
    label = pairs[:, 2] == 1
    n_pos = int(np.count_nonzero(label))
    curve = pr_curve(np.asarray(distances, dtype=np.float64), label, n_pos)
    metrics = summarize(curve, n_pos, len(pairs), f"pair list ({source})",
                        "the pair list is empty")
    metrics.update(n_pairs=int(len(pairs)), n_positives=n_pos,
                   n_negatives=int(len(pairs) - n_pos), pair_list=source,
                   pair_rule="each listed pair (i, j) is scored by the method's verification "
                             "score of j for query i; accepted when <= tau; no exclusion window")
    return PairListResult(pairs, np.asarray(distances, dtype=np.float64), curve, metrics)


def parse_pairs_option(text: str) -> tuple[str, int | None]:
    """``--pairs`` value: ``ssc`` / ``ssc:N`` (SSC's rule, N negatives per positive) or a file."""
    if text == "ssc" or text.startswith("ssc:"):
        ratio = 10
        if ":" in text:
            try:
                ratio = int(text.split(":", 1)[1])
            except ValueError:
                raise LirisError(f"--pairs {text}", "expected ssc:N with N an integer") from None
            if ratio < 1:
                raise LirisError(f"--pairs {text}", "N must be at least 1")
        return "ssc", ratio
    return "file", None


def evaluate_pair_list(seq, descriptors, pairs_text: str, *, cache=None, workers: int = 1,
                       progress: bool = False, executor=None) -> tuple[np.ndarray, list, dict]:
    """Score every descriptor on a pair list of ``seq``: ``(pairs, [(desc, db, result)], info)``.

    ``pairs_text`` is ``ssc``, ``ssc:N`` or a pair-list file (module docstring).
    """
    from lidar_iris_eval.extract import extract

    kind, ratio = parse_pairs_option(pairs_text)
    if kind == "ssc":
        frame = "camera" if seq.camera_poses is not None else "lidar"
        rule = SSCRule(negative_ratio=ratio, pose_frame=frame)
        pairs = ssc_pairs(seq.positions(frame), rule)
        info = {"pair_list": f"SSC rule, {ratio} negatives per positive, seed {rule.seed}",
                "pair_rule_source": rule.source, "pose_frame": frame}
        if not np.any(pairs[:, 2] == 1):
            raise LirisError(f"--pairs {pairs_text}", "the SSC rule finds no positive pair "
                                                      "(< 3 m, more than 50 frames apart)")
    else:
        pairs = read_pairs(pairs_text, len(seq))
        info = {"pair_list": str(Path(pairs_text).resolve())}
    results = []
    for desc in descriptors:
        db = extract(seq, desc, cache=cache, workers=workers, progress=progress,
                     executor=executor)
        import time

        t0 = time.perf_counter()
        distances = pair_distances_of(desc, desc.prepare(db.descriptors), pairs)
        res = score_pair_list(pairs, distances, info["pair_list"])
        res.metrics["match_us_per_pair"] = (time.perf_counter() - t0) / max(1, len(pairs)) * 1e6
        results.append((desc, db, res))
    return pairs, results, info
