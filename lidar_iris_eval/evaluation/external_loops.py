"""Score any system's loops against liris's ground truth (issue 35; docs/loops.md).

::

    from lidar_iris_eval.evaluation.external_loops import evaluate_loops
    from lidar_iris_eval.runs.writer import write_run

    run = evaluate_loops("sim/seq", ["slam/graph.g2o"], Settings(exclude=50))
    print(run.rows[0]["loops_precision"], run.rows[0]["revisit_coverage"])
    write_run(run, "results/slam-loops")      # liris show / compare read it

A file's loops (:mod:`lidar_iris_eval.io.loops`) become one "method" named
``loops:<file stem>`` in an ordinary protocol 1 run:

* **With a score per loop** (a ``matches.csv``, a scored pair list): each
  protocol 1 query keeps its best-scored loop (ties: the smaller match), a
  query without a loop has no match (never accepted), and the table goes
  through :func:`~lidar_iris_eval.evaluation.protocol1.score_protocol1`, the
  scorer every method uses: AP, F1max, R@100P, EP and the PR curve under the
  run's conventions. A run's own ``matches.csv`` therefore gives that run's
  numbers exactly.
* **Without a score** (a pose graph, an accepted-loop list): every loop is
  accepted. The row's protocol 1 numbers are those of a one-point curve (each
  query's first loop in file order, distance 0), and the ``loops_*`` keys
  count every loop (several per query allowed):
  ``loops_tp`` / ``loops_fp`` (ground-truth distance under / not under the
  radius), ``loops_precision = tp / (tp + fp)``, ``revisit_coverage`` = revisit
  queries with at least one true loop / revisit queries, ``loops_recall`` =
  the same count over the recall denominator (``revisits``: all revisit
  queries; ``accepted``: covered revisit queries + revisit queries with no
  loop at all), ``loops_f1`` their harmonic mean.

Loops the convention cannot score are kept out of every count and listed in
``loops.csv`` with their status: a query that is not a protocol 1 query
(``i < E``), or a match inside the exclusion window (``j > i - E``; the ground
truth holds no revisit there). Loops that carry a relative pose (g2o edges,
``T00..T23``) get the rotation / translation error against the ground-truth
relative pose (``evaluation/poses.py``) and ``loops_rr``: the share of true
loops with a full pose within 2 m and 5 deg.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from lidar_iris_eval.errors import LirisError, warn
from lidar_iris_eval.evaluation.evaluate import DescriptorResult, Evaluation, result_rows
from lidar_iris_eval.evaluation.ground_truth import (
    database_limits,
    ground_truth_for,
    pair_distances,
)
from lidar_iris_eval.evaluation.poses import pose_errors, relative_ground_truth
from lidar_iris_eval.evaluation.protocol1 import Protocol1Result, score_protocol1, scoring_rules
from lidar_iris_eval.evaluation.settings import Settings
from lidar_iris_eval.io.loops import (
    TIME_TOLERANCE,
    G2OGraph,
    Keyframes,
    LoopFile,
    place,
    read_keyframes,
    read_loops,
)
from lidar_iris_eval.matching.blocks import BestMatches

#: registration recall thresholds of the loops' own poses (as for methods)
RR_TRANSLATION_M = 2.0
RR_ROTATION_DEG = 5.0
LOOPS_RULE = ("accepted loops: TP when the ground-truth distance is under the radius; "
              "loops_precision = TP / (TP + FP) over every scored loop; revisit_coverage = "
              "revisit queries with a true loop / revisit queries; loops outside the "
              "protocol 1 queries or inside the exclusion window are listed, not scored")


@dataclass(frozen=True)
class LoopParams:
    """What a loop source records in ``config.yaml`` (``descriptors[].params``)."""

    path: str
    format: str
    sha256: str
    rule: str
    index_base: int = 0
    gap: int = 1
    scored: bool = False
    keyframes: str = ""  # how keyframe ids were placed on scans ("" : frame ids)
    time_tolerance_s: float = TIME_TOLERANCE
    coverage_tolerance_frames: int = 0
    posegraph_kernel: str = "none"
    odometry: str = ""  # --loops-odometry file, when given
    keyframe_times: str = ""  # --loops-times file, when given
    keyframe_map: str = ""  # --loops-map file, when given


@dataclass(frozen=True)
class LoopSource:
    """A loop file in the place of a descriptor (name ``loops:<stem>``, preset ``loops``)."""

    name: str
    params: LoopParams
    preset: str = "loops"
    two_stage: bool = False

    def run_info(self) -> dict[str, Any]:
        return {"loops_file": self.params.path, "loops_format": self.params.format}


@dataclass(frozen=True)
class NoDescriptors:
    """The ``db`` of a loop source: nothing was extracted (timing NaN, as externals)."""

    extract_s: np.ndarray
    read_s: np.ndarray | None = None
    extract_ms_per_scan: float | None = None
    warnings: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.extract_s)


@dataclass(frozen=True)
class LoopScore:
    """Every loop of one file scored: per-loop arrays (file order) and the protocol 1 result."""

    loops: LoopFile
    query: np.ndarray
    match: np.ndarray
    status: np.ndarray  # "true", "false", "not a query", "within window"
    dist_m: np.ndarray
    rre_deg: np.ndarray
    rte_m: np.ndarray
    protocol1: Protocol1Result
    metrics: dict = field(default_factory=dict)
    #: the pose-graph damage (g2o graphs with vertices; :mod:`.posegraph_damage`)
    damage: Any = None

    def table(self) -> dict[str, np.ndarray]:
        """Columns of ``loops/<name>/loops.csv``: one row per loop of the file."""
        cols = {"line": self.loops.line, "query": self.query, "match": self.match,
                "score": (self.loops.score if self.loops.score is not None
                          else np.full(len(self.query), np.nan)),
                "match_dist_m": self.dist_m, "status": self.status}
        if self.loops.pose is not None:
            cols["rre_deg"], cols["rte_m"] = self.rre_deg, self.rte_m
        return cols


def _per_query(query: np.ndarray, match: np.ndarray, score: np.ndarray | None,
               usable: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """Index (into the loops) of each query's loop, -1 for none: the best score (ties: the
    smaller match; NaN last), or the first in file order without scores."""
    chosen = np.full(len(queries), -1, dtype=np.int64)
    where = {int(q): k for k, q in enumerate(queries)}
    order = np.flatnonzero(usable)
    if score is not None:
        key = np.where(np.isnan(score[order]), np.inf, score[order])
        nan_last = np.isnan(score[order])
        order = order[np.lexsort((match[order], key, nan_last))]
    for k in order:
        slot = where[int(query[k])]
        if chosen[slot] < 0:
            chosen[slot] = k
    return chosen


def score_loops(loops: LoopFile, positions: np.ndarray, settings: Settings, *,
                lidar_poses: np.ndarray | None = None, frame_ids: np.ndarray | None = None,
                times: np.ndarray | None = None, forward: np.ndarray | None = None,
                scan_times: np.ndarray | None = None, keyframes: Keyframes | None = None,
                tolerance: float = TIME_TOLERANCE, coverage_tolerance: int = 0) -> LoopScore:
    """Score one file's loops under ``settings`` (module docstring for every rule).

    ``positions`` are the sequence's ``(N, 3)`` translations in
    ``settings.pose_frame``; ``lidar_poses`` ``(N, 4, 4)`` its LiDAR-frame poses
    (for the loops' pose errors); ``frame_ids`` map the file's ids to scans, or
    ``keyframes`` with the scans' ``scan_times`` (time stamps within ``tolerance`` s).
    ``times`` are the scan times the convention's window in seconds uses.
    ``coverage_tolerance`` (frames): a true loop's query covers the revisit
    frames within that many frames of it (:func:`coverage`).
    """
    n = len(positions)
    query, match = loops.indices(frame_ids, n, times=scan_times, keyframes=keyframes,
                                 tolerance=tolerance)
    gt = ground_truth_for(positions, settings, times)
    limits = database_limits(n, settings, times) if gt.limits is None else gt.limits
    is_query = limits[query] >= 0
    has = match >= 0
    inside = is_query & has & (match > limits[query])
    usable = is_query & has & ~inside
    dist_m = np.full(len(query), np.nan)
    if has.any():
        dist_m[has] = pair_distances(positions, query[has], match[has], gt.frame, gt.distance)
    inclusive = settings.inclusive_radius
    true = usable & ((dist_m <= gt.radius) if inclusive else (dist_m < gt.radius))
    status = np.where(true, "true", "false").astype(object)
    status[~has] = "no match"
    status[inside] = "within window"
    status[~is_query] = "not a query"
    for count, what in ((np.count_nonzero(~is_query), "have a query with no database under "
                         "the convention (i < E)"),
                        (np.count_nonzero(inside), "join frames inside the exclusion window "
                         "(j > i - E)")):
        if count:
            warn(loops.path, f"{count} of {len(query)} loops {what}: listed in loops.csv, "
                             "not scored")

    queries = np.flatnonzero(limits >= 0)
    chosen = _per_query(query, match, loops.score, usable, queries)
    got = chosen >= 0
    best_match = np.full(len(queries), -1, dtype=np.int64)
    best_match[got] = match[chosen[got]]
    distance = np.full(len(queries), np.inf)
    distance[got] = loops.score[chosen[got]] if loops.score is not None else 0.0
    pose = None
    if loops.pose is not None:
        pose = np.full((len(queries), 4, 4), np.nan)
        pose[got] = loops.pose[chosen[got]]
    best = BestMatches(query=queries, match=best_match, distance=distance,
                       yaw_deg=np.full(len(queries), np.nan), seconds=0.0, n_evaluations=0,
                       source=f"loops:{loops.format}", pose=pose)
    p1 = score_protocol1(best, positions, gt, forward=forward,
                         lidar_poses=lidar_poses if pose is not None else None,
                         **scoring_rules(settings))

    rre = np.full(len(query), np.nan)
    rte = np.full(len(query), np.nan)
    if loops.pose is not None and lidar_poses is not None and has.any():
        rre[has], rte[has] = pose_errors(loops.pose[has],
                                         relative_ground_truth(lidar_poses, query[has],
                                                               match[has]))
    metrics = _set_metrics(loops, query, usable, true, gt, settings, rre, rte)
    metrics.update(coverage(query[true], gt.revisit, coverage_tolerance))
    return LoopScore(loops, query, match, status.astype(str), dist_m, rre, rte, p1, metrics)


def revisit_stretches(revisit: np.ndarray) -> np.ndarray:
    """``(S, 2)`` first and last frame of each maximal run of consecutive revisit frames."""
    r = np.r_[False, np.asarray(revisit, dtype=bool), False].astype(np.int8)
    d = np.diff(r)
    return np.c_[np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1]


def coverage(true_queries: np.ndarray, revisit: np.ndarray, tolerance: int = 0) -> dict:
    """Revisit coverage of the true loops' queries, within ``tolerance`` frames.

    ``revisit_coverage``: revisit frames with a true loop's query within
    ``tolerance`` frames / revisit frames; ``revisit_stretch_coverage``: revisit
    stretches (maximal runs of consecutive revisit frames) that hold such a frame /
    stretches. ``tolerance`` 0: the query itself.
    """
    revisit = np.asarray(revisit, dtype=bool)
    n = len(revisit)
    mark = np.zeros(n + 1, dtype=np.int64)
    for q in np.unique(np.asarray(true_queries, dtype=np.int64)):
        mark[max(q - tolerance, 0)] += 1
        mark[min(q + tolerance + 1, n)] -= 1
    near = np.cumsum(mark[:n]) > 0
    stretches = revisit_stretches(revisit)
    touched = [bool(near[a:b + 1].any()) for a, b in stretches]
    return {"revisit_coverage": _ratio(int(np.count_nonzero(near & revisit)),
                                       int(np.count_nonzero(revisit))),
            "revisit_stretch_coverage": _ratio(sum(touched), len(stretches)),
            "n_revisit_stretches": int(len(stretches)),
            "n_revisit_stretches_covered": int(sum(touched)),
            "coverage_tolerance_frames": int(tolerance)}


def _ratio(a: float, b: float) -> float | None:
    return float(a / b) if b else None


def _set_metrics(loops, query, usable, true, gt, settings, rre, rte) -> dict:
    tp = int(np.count_nonzero(true))
    fp = int(np.count_nonzero(usable & ~true))
    revisit = gt.revisit
    covered = np.zeros(gt.n_frames, dtype=bool)
    covered[query[true]] = True
    covered &= revisit
    touched = np.zeros(gt.n_frames, dtype=bool)
    touched[query[usable]] = True
    n_covered = int(np.count_nonzero(covered))
    if settings.recall_denominator == "accepted":
        denominator = n_covered + int(np.count_nonzero(revisit & ~touched))
    else:
        denominator = gt.n_revisits
    precision = _ratio(tp, tp + fp)
    recall = _ratio(n_covered, denominator)
    f1 = (2 * precision * recall / (precision + recall)
          if precision is not None and recall is not None and precision + recall > 0 else
          (0.0 if precision is not None and recall is not None else None))
    out = {
        "n_loops": int(len(query)), "n_loops_scored": int(np.count_nonzero(usable)),
        "n_loops_unscored": int(len(query) - np.count_nonzero(usable)),
        "loops_tp": tp, "loops_fp": fp, "loops_precision": precision,
        "loops_recall": recall, "loops_f1": f1,
        "revisit_coverage": _ratio(n_covered, gt.n_revisits),
        "n_revisits_covered": n_covered, "loops_rule": LOOPS_RULE,
        "loops_scored_by": "score" if loops.score is not None else "accepted set",
    }
    if loops.format == "g2o":
        out["n_odometry_edges"] = loops.n_odometry_edges
    if loops.pose is not None:
        full = true & np.isfinite(rte)
        rot = true & np.isfinite(rre)
        out["loops_rre_deg_median"] = float(np.median(rre[rot])) if rot.any() else None
        out["loops_rte_m_median"] = float(np.median(rte[full])) if full.any() else None
        ok = full & (rte <= RR_TRANSLATION_M) & (rre <= RR_ROTATION_DEG)
        out["loops_rr"] = _ratio(int(np.count_nonzero(ok)), int(np.count_nonzero(full)))
        out["loops_rr_rule"] = (f"true loops with a full pose within {RR_TRANSLATION_M:g} m "
                                f"and {RR_ROTATION_DEG:g} deg of the ground-truth relative pose")
    return out


def source_names(paths: Sequence[str | os.PathLike]) -> list[str]:
    """``loops:<stem>`` per file, made unique with ``-2``, ``-3``... when stems repeat."""
    names: list[str] = []
    for p in paths:
        base = f"loops:{Path(p).stem}"
        name, k = base, 2
        while name in names:
            name, k = f"{base}-{k}", k + 1
        names.append(name)
    return names


def evaluate_loops(sequence, paths: Sequence[str | os.PathLike], settings: Settings | None = None,
                   *, formats: Sequence[str | None] | str | None = None, index_base: int = 0,
                   gap: int = 1, similarity: bool = False,
                   keyframe_times: str | os.PathLike | None = None,
                   keyframe_map: str | os.PathLike | None = None,
                   time_tolerance: float = TIME_TOLERANCE, posegraph: bool | None = None,
                   kernel: str = "none", kernel_k: float | None = None,
                   coverage_tolerance: int = 0,
                   odometry: str | os.PathLike | np.ndarray | None = None) -> Evaluation:
    """Score each loop file against ``sequence`` (a Sequence or a path) as one protocol 1 run.

    ``formats``: one format for all files, one per file, or None (detected).
    Returns an :class:`Evaluation` whose results are the files (``loops:<stem>``);
    :func:`lidar_iris_eval.runs.writer.write_run` writes it, and each result's
    ``loop_score`` attribute is its :class:`LoopScore` (see :func:`loop_scores`).

    Keyframe ids are placed on scans by ``keyframe_times`` (one time per
    keyframe) or ``keyframe_map`` (``keyframe scan`` lines), else they are
    frame ids. ``posegraph``: optimise g2o graphs (True), never (False), or
    when the file has vertices and gtsam is installed (None);
    ``kernel``/``kernel_k`` the robust kernel of the loop edges. ``odometry`` (a
    pose file or ``(N, 4, 4)`` LiDAR poses, one per scan) builds the graph for files
    whose loops carry poses (:func:`odometry_graph`).
    """
    settings = Settings() if settings is None else settings
    if isinstance(sequence, (str, os.PathLike)):
        from lidar_iris_eval.io import open_sequence

        sequence = open_sequence(sequence)
    if not paths:
        raise LirisError("--loops", "give at least one loop file")
    if formats is None or isinstance(formats, str):
        formats = [formats] * len(paths)
    if len(formats) != len(paths):
        raise LirisError("--loops-format", f"give one format, or one per --loops file "
                                           f"({len(paths)})")
    pose_frame = sequence.resolve_pose_frame(settings.pose_frame)
    if pose_frame != settings.pose_frame:
        settings = settings.replace(pose_frame=pose_frame)
    positions = sequence.positions(pose_frame)
    scan_times = getattr(sequence, "times", None)
    times = scan_times if settings.exclude_seconds is not None else None
    keyframes = read_keyframes(keyframe_times, keyframe_map)
    odometry_source = odometry if isinstance(odometry, (str, os.PathLike)) else None
    odometry = _odometry_poses(odometry, len(sequence))
    started = time.perf_counter()
    results = []
    for path, fmt, name in zip(paths, formats, source_names(paths), strict=True):
        loops = read_loops(path, fmt, index_base=index_base, gap=gap, similarity=similarity)
        scored = score_loops(loops, positions, settings, lidar_poses=sequence.poses,
                             frame_ids=getattr(sequence, "frame_ids", None), times=times,
                             forward=sequence.poses[:, :3, 0], scan_times=scan_times,
                             keyframes=keyframes, tolerance=time_tolerance,
                             coverage_tolerance=coverage_tolerance)
        damage = _damage(loops, scored, sequence, scan_times, keyframes, time_tolerance,
                         posegraph, kernel, kernel_k, odometry)
        if damage is not None:
            scored = replace(scored, damage=damage)
        digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
        source = LoopSource(name, LoopParams(str(Path(path).resolve()), loops.format, digest,
                                             loops.rule, index_base, gap,
                                             loops.score is not None,
                                             keyframes.rule if keyframes is not None else "",
                                             time_tolerance, coverage_tolerance, kernel,
                                             _resolved(odometry_source),
                                             _resolved(keyframe_times),
                                             _resolved(keyframe_map)))
        db = NoDescriptors(np.full(len(sequence), np.nan))
        rows = result_rows(source, db, scored.protocol1, None, settings)
        rows[0]["match_ms_per_query"] = None  # computed elsewhere
        rows[0].update(scored.metrics)
        if keyframes is not None:
            rows[0]["loops_keyframes"] = keyframes.rule
        if damage is not None:
            rows[0].update(damage.summary())
        results.append(LoopResult(source, db, scored.protocol1, None, rows, loop_score=scored))
    return Evaluation(sequence, settings, (1,), pose_frame, results,
                      time.perf_counter() - started)


@dataclass(frozen=True)
class LoopResult(DescriptorResult):
    """A :class:`DescriptorResult` that also holds the file's :class:`LoopScore`."""

    loop_score: LoopScore | None = None

    def extra_files(self) -> dict[str, dict]:
        """Run-folder tables of this source: ``loops/<name>/loops.csv`` (every loop) and,
        for a pose graph, ``loops/<name>/posegraph.csv`` (the APE table)."""
        if self.loop_score is None:
            return {}
        base = f"loops/{self.descriptor.name}"
        out = {f"{base}/loops.csv": self.loop_score.table()}
        if self.loop_score.damage is not None:
            out[f"{base}/posegraph.csv"] = self.loop_score.damage.table()
        return out


def loop_scores(evaluation: Evaluation) -> dict[str, LoopScore]:
    """``{name: LoopScore}`` of the loop sources of an evaluation."""
    return {r.descriptor.name: r.loop_score for r in evaluation.results
            if getattr(r, "loop_score", None) is not None}


#: the edge sigmas of a graph built from --loops-odometry (no information in the files)
ODOMETRY_SIGMA_M, ODOMETRY_SIGMA_RAD = 0.1, 0.01


def odometry_graph(odometry: np.ndarray, loops: LoopFile, query: np.ndarray,
                   match: np.ndarray) -> tuple[G2OGraph, np.ndarray]:
    """A pose graph from an odometry (one LiDAR pose per scan) and a file's loop poses.

    Vertex ``k`` is scan ``k`` at its odometry pose; an edge joins each pair of
    consecutive scans (their odometry motion) and each loop with a full pose (the
    match's pose in the query's frame). Every edge gets the same information
    (sigma 0.1 m, 0.01 rad; g2o order). Returns the graph and each loop's edge index
    (-1: no usable pose).
    """
    info = np.diag([1 / ODOMETRY_SIGMA_M**2] * 3 + [4 / ODOMETRY_SIGMA_RAD**2] * 3)
    n = len(odometry)
    edges = [(k, k + 1, np.linalg.inv(odometry[k]) @ odometry[k + 1], info)
             for k in range(n - 1)]
    index = np.full(len(query), -1, dtype=np.int64)
    for k, (q, m) in enumerate(zip(query, match, strict=True)):
        T = loops.pose[k] if loops.pose is not None else None
        if m < 0 or T is None or not np.isfinite(T).all():
            continue
        index[k] = len(edges)
        edges.append((int(q), int(m), T, info))
    graph = G2OGraph({k: odometry[k] for k in range(n)}, edges, [0])
    return graph, index


def _damage(loops: LoopFile, scored: LoopScore, sequence, scan_times, keyframes, tolerance,
            posegraph: bool | None, kernel: str, kernel_k: float | None,
            odometry: np.ndarray | None = None):
    """The pose-graph damage of a g2o file with vertices (or of any file's loop poses on
    ``odometry``), or None (module docstring)."""
    if odometry is not None and posegraph is not False:
        from lidar_iris_eval.evaluation.posegraph_damage import KERNEL_K, posegraph_damage

        graph, index = odometry_graph(odometry, loops, scored.query, scored.match)
        if not (index >= 0).any():
            warn(loops.path, "no loop carries a full pose: no pose-graph damage from "
                             "--loops-odometry")
            return None
        return posegraph_damage(graph, index, scored.status,
                                {k: k for k in range(len(odometry))},
                                sequence.poses[:, :3, 3], kernel=kernel,
                                kernel_k=KERNEL_K if kernel_k is None else kernel_k)
    graph = loops.graph
    usable = (graph is not None and bool(graph.vertices) and len(loops) > 0
              and loops.n_odometry_edges > 0)
    if posegraph is False or (posegraph is None and not usable):
        return None
    if not usable:
        raise LirisError(loops.path, "pose-graph damage needs a g2o pose graph with vertices, "
                                     "odometry edges and loop edges")
    if posegraph is None and importlib.util.find_spec("gtsam") is None:
        warn(loops.path, "gtsam is not installed: no pose-graph damage (pip install "
                         "'lidar_iris_eval[posegraph]')")
        return None
    from lidar_iris_eval.evaluation.posegraph_damage import KERNEL_K, posegraph_damage

    ids = np.array(sorted(graph.vertices), dtype=np.int64)
    lines = np.array([graph.vertex_lines[v] for v in ids], dtype=np.int64)
    scans = place(ids, lines, loops.path, len(sequence), getattr(sequence, "frame_ids", None),
                  scan_times, keyframes, tolerance)
    return posegraph_damage(graph, loops.extra["edge_index"], scored.status,
                            dict(zip(ids.tolist(), scans.tolist(), strict=True)),
                            sequence.poses[:, :3, 3], kernel=kernel,
                            kernel_k=KERNEL_K if kernel_k is None else kernel_k)


def _resolved(path) -> str:
    return "" if path is None else str(Path(path).resolve())


def _odometry_poses(odometry, n_frames: int) -> np.ndarray | None:
    """``(N, 4, 4)`` odometry poses from a KITTI/TUM file (or an array), one per scan."""
    if odometry is None:
        return None
    if isinstance(odometry, (str, os.PathLike)):
        from lidar_iris_eval.io.poses import read_pose_file

        source = str(odometry)
        _, poses = read_pose_file(odometry)
    else:
        source, poses = "odometry", np.asarray(odometry, dtype=np.float64)
    if poses.shape != (n_frames, 4, 4):
        raise LirisError(f"--loops-odometry {source}", f"needs one pose per scan: "
                                                       f"{len(poses)} poses, {n_frames} scans")
    return poses
