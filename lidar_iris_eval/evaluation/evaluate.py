"""The evaluation as a library call: what ``liris eval`` runs, importable.

::

    from lidar_iris_eval.evaluation.evaluate import Settings, evaluate
    from lidar_iris_eval.runs.writer import write_run

    run = evaluate("dataset/sequences/00", ["lidar-iris", "scan-context:reference"],
                   protocols=(1, 2), settings=Settings(exclude="reference"),
                   cache=".liris-cache")
    for row in run.rows:                       # the rows of metrics.json
        print(row["protocol"], row["descriptor"], row["f1_max"], row.get("rre_deg_median"))
    write_run(run, "results/kitti00")         # the run folder (docs/results-format.md)

:func:`evaluate` extracts (or loads) descriptors, runs the requested
protocols under frozen :class:`Settings`, and returns an :class:`Evaluation`
holding every result object, the metric rows, the header (conventions) and
the config. It writes nothing; :func:`lidar_iris_eval.runs.writer.write_run` lays a run
folder out and
:func:`export_loops` writes accepted loops as pose-graph edges.
"""

from __future__ import annotations

import os
import platform
import sys
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lidar_iris_eval import __version__
from lidar_iris_eval.config import params_dict
from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.errors import LirisError, option
from lidar_iris_eval.evaluation import loop_poses as lp
from lidar_iris_eval.evaluation import metrics as m
from lidar_iris_eval.evaluation import poses as pose_tools
from lidar_iris_eval.evaluation.conventions import convention_header
from lidar_iris_eval.evaluation.ground_truth import database_limits
from lidar_iris_eval.evaluation.metrics import SUMMARY_KEYS
from lidar_iris_eval.evaluation.protocol1 import REVERSE_DEGREES, Protocol1Result, protocol1
from lidar_iris_eval.evaluation.protocol2 import Protocol2Result, protocol2, protocols_1_and_2
from lidar_iris_eval.evaluation.settings import EXCLUDE_PRESETS, Settings
from lidar_iris_eval.extract import DescriptorDB, extract_many

__all__ = [
    "EXCLUDE_PRESETS",
    "DescriptorResult",
    "Evaluation",
    "Settings",
    "evaluate",
    "export_loops",
]


def host_info() -> dict[str, Any]:
    """Python, platform, CPU count and load average: the conditions of a run's timings
    (wall-clock matching slows on a busy host)."""
    return {"python": sys.version.split()[0], "platform": platform.platform(),
            "cpu_count": os.cpu_count(),
            "load_average_1_5_15min": [round(v, 2) for v in os.getloadavg()]}


def run_header(run: Any, config: dict) -> dict[str, Any]:
    """The fields that open every metrics.json header, in this order: version,
    when the run was made, how long it took, the host (see :func:`host_info`)
    and the sequence. A run of one sequence and a cross-session run both start
    here, so a reader finds them under the same names."""
    return {"version": __version__, "created": run.created, "wall_s": run.wall_s,
            "host": host_info(), "sequence": config["sequence"]}


@dataclass(frozen=True)
class DescriptorResult:
    """Everything computed for one descriptor."""

    descriptor: Descriptor
    db: DescriptorDB
    protocol1: Protocol1Result | None
    protocol2: Protocol2Result | None
    rows: list[dict]
    #: registration of the protocol 1 matches (issue 23), when asked for
    loop_poses: lp.LoopPoses | None = None
    #: ``--convention-band``: ``(values per preset, skipped presets, PR curve per preset)``
    band: tuple[dict, dict, dict] | None = None


@dataclass(frozen=True)
class Evaluation:
    """Results of :func:`evaluate` (``rows`` are the ``results`` of metrics.json)."""

    sequence: Any
    settings: Settings
    protocols: tuple[int, ...]
    pose_frame: str
    results: list[DescriptorResult]
    wall_s: float
    created: str = field(default_factory=lambda: datetime.now().isoformat(timespec="seconds"))
    loop_settings: lp.LoopPoseSettings = field(default_factory=lp.LoopPoseSettings)
    #: ``--seeds``: {(protocol, descriptor): [(seed, PRCurve)]} of stochastic methods
    seed_curves: dict = field(default_factory=dict)

    @property
    def rows(self) -> list[dict]:
        return [row for r in self.results for row in r.rows]

    def config(self, **extra) -> dict:
        """Everything needed to reproduce the run (``config.yaml``); ``extra`` is merged
        in (e.g. the CLI's sensor and reader options)."""
        seq = self.sequence
        s = self.settings
        config = {
            "version": __version__,
            "sequence": {"path": str(Path(seq.path).resolve()), "name": seq.name,
                         "n_frames": len(seq), "fingerprint": seq.fingerprint()},
            "descriptors": [{"name": r.descriptor.name, "preset": r.descriptor.preset,
                             "params": params_dict(r.descriptor.params)} for r in self.results],
            "protocols": list(self.protocols),
            "pose_frame": self.pose_frame,  # the frame used (camera falls back to lidar)
            "candidates": s.candidates,
            "block_pairs": int(s.pair_budget),
            "convention": s.to_dict(),  # Settings.from_dict rebuilds the run's ground truth
            **self.loop_settings.config(),
        }
        for key, value in extra.items():
            if key == "reader_options":
                config["sequence"]["reader_options"] = {  # flags and numbers stay typed
                    k: v if v is None or isinstance(v, (bool, int, float)) else str(v)
                    for k, v in value.items()}
            else:
                config[key] = value
        return config

    def header(self, config: dict | None = None) -> dict:
        """The metrics.json header: version, host, sequence and every convention."""
        config = self.config() if config is None else config
        s = self.settings
        return {
            **run_header(self, config),
            "conventions": {
                "radius": float(s.radius),
                "exclude": None if s.exclude_seconds is not None else int(s.exclude),
                "exclude_preset": s.exclude_name,
                "distance": s.distance,
                "pose_frame": self.pose_frame,
                "recall_denominator": s.recall_denominator,
                "candidates": s.candidates,
                "positive": f"ground-truth distance < {float(s.radius):g} m",
                "threshold_rule": m.THRESHOLD_RULE,
                "ap": m.AP_DEFINITION,
                "ep": m.EP_DEFINITION,
                "protocol2_counts": "ordered pairs (i, j), i != j",
                "reverse_revisit": f"nearest earlier positive's heading differs by > "
                                   f"{REVERSE_DEGREES:g} deg (LiDAR x axis)",
                "relative_pose": "T maps points of the matched scan's LiDAR frame into the "
                                 "query's LiDAR frame (matches.csv T00..T23, row-major 3x4)",
                "pose_error": pose_tools.POSE_ERROR_RULE,
                "extract_time": "mean per-thread CPU time of descriptor.compute per scan "
                                "(compilation excluded), from the run that filled the cache",
                "match_time": "wall time of the matching loop after an untimed warm-up call "
                              "of its kernels (compilation excluded)",
                **convention_header(config.get("convention")),
                **self.loop_settings.conventions(),
                **({"odometry": config["odometry"], "odometry_rule": ODOMETRY_RULE}
                   if config.get("odometry") else {}),
                **({"convention_band": _band_rule()}
                   if any(r.band is not None for r in self.results) else {}),
            },
        }


def _band_rule() -> str:
    from lidar_iris_eval.evaluation.band import BAND_RULE

    return BAND_RULE


#: what ``--odometry`` means, for the metrics.json header
ODOMETRY_RULE = ("pose source of the local maps of methods that read them: gt = the sequence's "
                 "poses (an oracle), kiss-icp = estimated from the scans alone; the ground "
                 "truth of the protocols and the pose errors always use the sequence's poses")


def bind_exclusion(descriptors, exclude: int) -> list:
    """Descriptors with their local-map window bound to the exclusion window E.

    A method that reads local maps (``bind_exclusion`` method) builds frame i's
    map from the scans of frames ``i - E < j <= i``, so a query's map never
    holds a database scan; the window enters its parameters (and cache key).
    """
    return [d.bind_exclusion(exclude) if hasattr(d, "bind_exclusion") else d
            for d in descriptors]


def _descriptor_list(descriptors) -> list[Descriptor]:
    from lidar_iris_eval.descriptors import get_descriptor

    if isinstance(descriptors, (str, Descriptor)):
        descriptors = [descriptors]
    out = []
    for d in descriptors:
        if isinstance(d, str):
            name, _, preset = d.partition(":")
            d = get_descriptor(name, preset or None)
        out.append(d)
    names = [d.name for d in out]
    if not out or len(set(names)) != len(names):
        raise LirisError(option("descriptors", names), "give each descriptor once")
    return out


def check_request(descriptors: Sequence[Descriptor], protocols: Iterable[int],
                  settings: Settings) -> tuple[int, ...]:
    """Validate protocols and the retrieval setting before any work; sorted protocols."""
    protocols = tuple(sorted({int(p) for p in protocols}))
    if not protocols or set(protocols) - {1, 2}:
        raise LirisError(option("protocols", protocols), "protocols are 1 and/or 2")
    if settings.candidates is not None:
        for d in descriptors:
            if not d.has_retrieval():
                raise LirisError(option("candidates", settings.candidates),
                                 f"{d.name} has no retrieval stage")
        if not any(d.two_stage for d in descriptors) and 1 not in protocols:
            raise LirisError(option("candidates", settings.candidates),
                             "only applies to protocol 1 (and two-stage methods)")
    return protocols


def evaluate(
    sequence,
    descriptors: Descriptor | str | Iterable[Descriptor | str],
    protocols: Iterable[int] = (1, 2),
    settings: Settings | None = None,
    *,
    cache: Any = None,
    workers: int = 1,
    progress: bool = False,
    dbs: Sequence[DescriptorDB] | None = None,
    convention: Settings | None = None,
    executor: Any = None,
    loop_settings: lp.LoopPoseSettings | None = None,
    ranking: bool = False,
    convention_band: bool = False,
) -> Evaluation:
    """Extract and evaluate ``descriptors`` on ``sequence`` under ``settings``.

    Parameters
    ----------
    sequence : a :class:`~lidar_iris_eval.io.Sequence` or a path for
        :func:`~lidar_iris_eval.io.open_sequence`.
    descriptors : descriptor objects or names (``"name"`` or ``"name:preset"``).
    protocols : any of 1 and 2.
    settings : every convention (default :class:`Settings()`); a peer preset
        (:func:`~lidar_iris_eval.evaluation.conventions.get_convention`) is one.
    cache : a :class:`~lidar_iris_eval.cache.DescriptorCache`, a folder, or None.
    workers : extraction processes (when no ``executor`` is given).
    progress : tqdm bars on stderr.
    dbs : already extracted descriptors (one per descriptor), to skip extraction.
    convention : a preset whose ground-truth rules replace those of
        ``settings`` (``candidates`` and ``pair_budget`` are kept); what is
        scored is what the run records.
    executor : from :func:`~lidar_iris_eval.executor.open_executor`; runs the
        extraction chunks and block passes (default: serial / a local pool of
        ``workers``).
    loop_settings : registration recall thresholds, ``--refine``, ``--gt-pose``
        (:mod:`~lidar_iris_eval.evaluation.loop_poses`); default: RR at 2 m / 5 deg only.
    ranking : also rank every protocol 1 query's database (Recall@1..25,
        Recall@1 %, MRR in the protocol 1 row; one more matching pass,
        :func:`ranking_row`).
    convention_band : also score protocol 1 under every convention preset that
        applies to the run, from the same matching pass
        (:mod:`~lidar_iris_eval.evaluation.band`); each protocol 1 row gets a
        ``convention_band`` entry.
    """
    settings = Settings() if settings is None else settings
    if convention is not None:
        settings = convention.replace(candidates=settings.candidates,
                                      pair_budget=settings.pair_budget)
    loop_settings = lp.LoopPoseSettings() if loop_settings is None else loop_settings
    descriptors = _descriptor_list(descriptors)
    # local-map methods build each frame's map from the last E frames (never a database scan)
    descriptors = bind_exclusion(descriptors, settings.exclude)
    protocols = check_request(descriptors, protocols, settings)
    if isinstance(sequence, (str, os.PathLike)):
        from lidar_iris_eval.io import open_sequence

        sequence = open_sequence(sequence)
    for d in descriptors:
        d.check_inputs(sequence)
    pose_frame = sequence.resolve_pose_frame(settings.pose_frame)
    if pose_frame != settings.pose_frame:  # the frame the numbers are computed in
        settings = settings.replace(pose_frame=pose_frame)
    positions = sequence.positions(pose_frame)
    forward = sequence.poses[:, :3, 0]  # LiDAR x axis: the driving direction
    started = time.perf_counter()
    if dbs is None:
        dbs = extract_many(sequence, descriptors, cache=cache, workers=workers,
                           progress=progress, executor=executor)  # one read per scan
    times = getattr(sequence, "times", None) if settings.exclude_seconds is not None else None
    plan = None
    if convention_band:
        plan = _band_plan(sequence, settings, pose_frame, protocols, loop_settings)
    matched = [_evaluate_one(desc, db, positions, forward, sequence.poses, protocols,
                             settings, progress, times, executor, plan,
                             getattr(sequence, "times", None))
               for desc, db in zip(descriptors, dbs, strict=True)]
    # every method's registrations in one call: scans prepared once for the run
    loops = lp.register_all([r.protocol1 for r in matched], sequence, loop_settings,
                            ",".join(d.name for d in descriptors), progress, executor)
    results = []
    for desc, db, result, loop in zip(descriptors, dbs, matched, loops, strict=True):
        if result.protocol1 is not None:
            result = _with_loop_poses(result, sequence, positions, forward, settings,
                                      loop_settings, progress, executor, loop)
        if ranking and result.protocol1 is not None:
            result.rows[0].update(ranking_row(desc, db, positions, settings, times))
        if result.band is not None:
            from lidar_iris_eval.evaluation.band import band_block

            values, skipped, _ = result.band
            result.rows[0]["convention_band"] = band_block(result.rows[0], settings.name,
                                                           values, skipped)
        results.append(result)
    return Evaluation(sequence, settings, protocols, pose_frame, results,
                      time.perf_counter() - started, loop_settings=loop_settings)


def _with_loop_poses(result: DescriptorResult, sequence, positions, forward, settings,
                     loop_settings: lp.LoopPoseSettings, progress,
                     executor=None, loops: lp.LoopPoses | None = None) -> DescriptorResult:
    """Registration recall, and with ``--refine``/``--gt-pose refined`` the registrations
    (issue 23): protocol 1 rescored under the acceptance rule, its row extended."""
    p1, loops = lp.apply(result.protocol1, sequence, positions, forward, loop_settings,
                         desc_name=result.descriptor.name, progress=progress,
                         run_settings=settings, executor=executor, loops=loops)
    rows = result_rows(result.descriptor, result.db, p1, result.protocol2, settings) \
        if p1 is not result.protocol1 else [dict(r) for r in result.rows]
    rows[0].update(lp.loop_pose_metrics(p1, loops, loop_settings,
                                        points=lp.has_points(sequence)))
    return replace(result, protocol1=p1, rows=rows, loop_poses=loops)


def _band_plan(sequence, settings: Settings, pose_frame: str, protocols, loop_settings):
    """The presets of ``--convention-band`` (refused where it would not mean one pass)."""
    from lidar_iris_eval.evaluation.band import band_plan

    if 1 not in protocols:
        raise LirisError("--convention-band", "scores protocol 1; add --protocol 1")
    if loop_settings.refine is not None or loop_settings.gt_pose != "dataset":
        raise LirisError("--convention-band", "the band scores the plain protocol 1 matches; "
                         "it does not combine with --refine or --gt-pose refined")
    return band_plan(sequence, settings, pose_frame)


def _evaluate_one(desc, db, positions, forward, lidar_poses, protocols, settings, progress,
                  times=None, executor=None, plan=None, seq_times=None) -> DescriptorResult:
    """Run the requested protocols for one descriptor and build its metric rows.

    Protocols 1 and 2 are reducers of one block pass when both are asked
    for (a two-stage method runs its retrieval passes); the kind of method
    is the matcher's business, not this function's.
    """
    s = settings
    p1 = p2 = None
    n = len(db)
    limits = database_limits(n, s, times)
    rows_to_match = n if 2 in protocols else int(np.count_nonzero(limits >= 0))
    common = dict(forward=forward, lidar_poses=lidar_poses, executor=executor)
    keep: list[int] = []
    left: dict[str, str] = {}
    if plan is not None:
        from lidar_iris_eval.evaluation.band import usable_presets

        keep, left = usable_presets(plan, desc, s, limits)
        left = {**plan.skipped, **left}
        if keep:
            common["band_limits"] = plan.limits[keep]
    with tqdm(total=rows_to_match, desc=f"{desc.name} matching", unit="query",
              file=sys.stderr, disable=not progress, leave=False) as bar:
        if protocols == (1, 2):  # the matchers pick the path from the method and candidates
            p1, p2 = protocols_1_and_2(desc, db.descriptors, positions, s, times=times,
                                       progress=bar.update, **common)
        elif protocols == (1,):
            p1 = protocol1(desc, db.descriptors, positions, s, times=times,
                           progress=bar.update, **common)
        else:  # candidates is K of a two-stage method; protocol2 ignores it otherwise
            p2 = protocol2(desc, db.descriptors, positions, s, progress=bar.update,
                           executor=executor)
    band = None
    if plan is not None:
        from lidar_iris_eval.evaluation.band import score_band

        values, curves = score_band(p1.band_matches or (), positions,
                                    [plan.presets[k] for k in keep], plan.limits[keep],
                                    seq_times)
        band = (values, left, curves)
    return DescriptorResult(desc, db, p1, p2, result_rows(desc, db, p1, p2, s), band=band)


def ranking_row(desc, db, positions, settings: Settings, times=None) -> dict:
    """Recall@1..25, Recall@1 % and MRR of protocol 1's queries over their own databases.

    The database of query ``i`` is what protocol 1 allows (``j <= limits[i]``);
    positives are the frames within the radius there. Recall@1 equals
    protocol 1's top-1 accuracy over revisit queries (``n_true_top1 /
    n_revisits``) under the standard rule.
    """
    from lidar_iris_eval.evaluation.cross_session import cross_positives, evaluate_sessions
    from lidar_iris_eval.evaluation.ground_truth import gt_coordinates

    limits = database_limits(len(db), settings, times)
    coords = gt_coordinates(positions, settings.pose_frame, settings.distance)
    positives = cross_positives(coords, coords, settings.radius, settings.inclusive_radius)
    res = evaluate_sessions(desc, db, db, positives, limits=limits, same_sequence=True,
                            candidates=settings.candidates, pair_budget=settings.pair_budget,
                            label="ranking")
    keys = ("recall_at_1", "recall_at_1pct", "recall_1pct_n", "mrr", "mrr_top25_found",
            "recall_at_n", "n_ranking_queries", "ranking_definition", "ranking_rule")
    return {k: res.metrics[k] for k in keys}


def _pose_kind(p1: Protocol1Result) -> str:
    """``full`` (6-DoF), ``yaw`` (rotation only) or ``none`` — what the method estimated."""
    if p1.pose is None:
        return "none"
    has = p1.matches.match >= 0
    rot = np.isfinite(p1.pose[has, :3, :3]).all(axis=(1, 2))
    trans = np.isfinite(p1.pose[has, :3, 3]).all(axis=1)
    if trans.any():
        return "full"
    return "yaw" if rot.any() else "none"


def _odometry_ms(db, source: str) -> float | None:
    """Mean CPU ms per scan of the odometry that placed the local maps (None: ``gt``, an
    oracle that costs nothing, or features without the ``odometry_s`` key)."""
    values = getattr(getattr(db, "descriptors", None), "values", None)
    if source == "gt" or values is None or "odometry_s" not in values:
        return None
    seconds = np.asarray(values["odometry_s"], dtype=np.float64)
    return float(seconds.mean() * 1e3) if len(seconds) else None


def result_rows(desc, db, p1, p2, settings) -> list[dict]:
    """The ``metrics.json`` rows of one method (one per protocol scored): what every method
    and every ``--loops`` source (evaluation/external_loops.py) reports."""
    base = {"descriptor": desc.name, "preset": desc.preset, **desc.run_info()}
    if "odometry" in base:  # a local-map method: what its odometry cost per scan
        base["odometry_ms_per_scan"] = _odometry_ms(db, base["odometry"])
    qualifiers = list(getattr(db, "warnings", ()) or ())
    if qualifiers:  # a warning that qualifies the numbers travels with them (runs/schema.py)
        base["warnings"] = qualifiers
    rows = []
    if p1 is not None:
        matches = p1.matches
        n_queries = max(1, p1.metrics["n_queries"])
        rows.append({
            "protocol": 1, **base, **{k: p1.metrics[k] for k in SUMMARY_KEYS},
            "n_queries": p1.metrics["n_queries"],
            "n_positives": p1.metrics["n_positives"],
            "n_revisits": p1.metrics["n_revisits"],
            "extract_ms_per_scan": db.extract_ms_per_scan,
            "match_ms_per_query": (matches.seconds / n_queries * 1e3 if p1.metrics["n_queries"]
                                   else float("nan")),  # no query: no time per query
            "recall_denominator": settings.recall_denominator,
            "match_source": matches.source,
            "pose_estimate": _pose_kind(p1),
            **{k: v for k, v in p1.metrics.items()
               if k not in SUMMARY_KEYS and k not in ("n_queries", "n_positives", "n_revisits")},
        })
    if p2 is not None:
        aff = p2.affinity
        rows.append({
            "protocol": 2, **base, **{k: p2.metrics[k] for k in SUMMARY_KEYS},
            "n_pairs": p2.metrics["n_pairs"],
            "n_positives": p2.metrics["n_positives"],
            "n_negatives": p2.metrics["n_negatives"],
            "extract_ms_per_scan": db.extract_ms_per_scan,
            "match_us_per_pair": (aff.seconds / aff.n_evaluations * 1e6
                                  if aff.n_evaluations and p2.metrics["n_pairs"]
                                  else float("nan")),  # no pair: no time per pair
            "n_distance_evaluations": aff.n_evaluations,
            "symmetric": aff.symmetric,
            "p_at_lowest_recall": p2.metrics["p_at_lowest_recall"],
            "protocol2_rule": p2.metrics["protocol2_rule"],
            **{k: p2.metrics[k] for k in ("affinity_stored", "pr_counting") if k in p2.metrics},
        })
    return rows


def loop_export_paths(path: str | os.PathLike, names: Sequence[str]) -> list[Path]:
    """One file per descriptor: ``path`` itself for one, ``<stem>-<name><suffix>`` for several."""
    path = Path(path)
    if len(names) == 1:
        return [path]
    return [path.with_name(f"{path.stem}-{name}{path.suffix}") for name in names]


def export_loops(evaluation: Evaluation, path: str | os.PathLike,
                 vertex_poses: np.ndarray | None = None) -> dict[str, tuple[Path, int]]:
    """Write each descriptor's accepted protocol 1 loops at its F1max threshold.

    Returns ``{descriptor: (file, loops written)}``; formats in
    :mod:`~lidar_iris_eval.evaluation.loop_export`. Refined loops (``--refine``)
    are written with their refined pose and a fitness-derived information;
    ``.g2o`` vertices are ``vertex_poses`` (an odometry, LiDAR frame) or the
    sequence's LiDAR-frame poses.
    """
    from lidar_iris_eval.evaluation.loop_export import export_loop_file

    with_p1 = [r for r in evaluation.results if r.protocol1 is not None]
    if not with_p1:
        raise LirisError(option("export_loops", path), "loop export needs protocol 1")
    out = {}
    for r, target in zip(with_p1, loop_export_paths(path, [r.descriptor.name for r in with_p1]),
                         strict=True):
        p1 = r.protocol1
        tau = p1.metrics["f1_threshold"]
        f1 = p1.metrics.get("f1_max")
        matches = p1.matches
        usable = f1 is not None and np.isfinite(f1) and f1 > 0 and tau is not None \
            and np.isfinite(tau)
        if not usable:
            # F1max 0 (or undefined): the threshold is then the curve's first point and
            # every edge it accepts is false; a pose graph must not get them
            from lidar_iris_eval.errors import warn

            warn(option("export_loops", target), f"{r.descriptor.name}: F1max is "
                 f"{'undefined' if f1 is None or not np.isfinite(f1) else f'{f1:g}'}, so no "
                 "threshold separates true loops; no loops written")
        accepted = (matches.match >= 0) & (matches.distance <= tau) if usable else \
            np.zeros(len(matches.match), bool)
        pose = p1.pose if p1.pose is not None else np.full((len(matches.match), 4, 4), np.nan)
        ratio = rmse = None
        refined = r.loop_poses.refined if r.loop_poses is not None else None
        if refined is not None:
            pose = np.where(refined.registered[:, None, None], refined.pose, pose)
            ratio, rmse = refined.inlier_ratio[accepted], refined.rmse_m[accepted]
        seq = evaluation.sequence
        written = export_loop_file(
            target, matches.query[accepted], matches.match[accepted], pose[accepted],
            vertex_poses=seq.poses if vertex_poses is None else vertex_poses,
            frame_ids=getattr(seq, "frame_ids", None), times=getattr(seq, "times", None),
            inlier_ratio=ratio, rmse_m=rmse)
        out[r.descriptor.name] = (target, written)
    return out
