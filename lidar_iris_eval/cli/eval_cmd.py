"""``liris eval``: protocol 1 and/or 2 for one or more descriptors, written to a run folder.

Parsing only: the options become one frozen
:class:`~lidar_iris_eval.cli.eval_request.EvalRequest`, and :func:`mode_of`
picks the function that runs, writes and prints it (one sequence:
:mod:`~lidar_iris_eval.cli.sequence_eval`; several sequences or a plan:
:mod:`~lidar_iris_eval.cli.eval_many`; a query/database pair:
:mod:`~lidar_iris_eval.cli.sessions_eval`; a plan of pairs:
:mod:`~lidar_iris_eval.cli.sessions_plan`; a pair list:
:mod:`~lidar_iris_eval.cli.pairs_eval`; loop files:
:mod:`~lidar_iris_eval.cli.loops_eval`). Each mode checks the options it
needs; the evaluation itself is :func:`lidar_iris_eval.evaluation.evaluate.evaluate`.
"""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.cli.descriptor_options import descriptor_options
from lidar_iris_eval.cli.eval_many import run_many
from lidar_iris_eval.cli.eval_request import EvalRequest
from lidar_iris_eval.cli.loop_options import loop_pose_options
from lidar_iris_eval.cli.loops_eval import loops_options, run_loops
from lidar_iris_eval.cli.options import current_convention, ground_truth_options
from lidar_iris_eval.cli.pairs_eval import run_pairs
from lidar_iris_eval.cli.sequence_eval import run_sequence
from lidar_iris_eval.cli.sessions_eval import run_sessions
from lidar_iris_eval.cli.sessions_plan import is_sessions_plan, run_sessions_plan
from lidar_iris_eval.cli.workflow import (
    config_extra,
    external_options,
    table_format,
    workflow_options,
)
from lidar_iris_eval.errors import register_flags
from lidar_iris_eval.evaluation.evaluate import loop_export_paths
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET

#: library keywords (Settings, evaluate) -> the flags that set them, for error messages
register_flags({
    "radius": "--radius", "exclude": "--exclude", "distance": "--distance",
    "pose_frame": "--pose-frame", "recall_denominator": "--recall-denominator",
    "candidates": "--candidates", "pair_budget": "--block-pairs", "protocols": "--protocol",
    "descriptors": "--descriptor", "export_loops": "--export-loops", "workers": "--workers",
})


@click.command("eval")
@workflow_options
@loop_pose_options
@click.argument("sequence", nargs=-1, type=click.Path(path_type=Path))
@click.option("--protocol", "protocols", type=click.Choice(["1", "2"]), multiple=True,
              help="1 (best match per query) or 2 (all pairs); may be repeated. Required "
                   "for a SEQUENCE; a --query/--database run has its own protocol.")
@click.option("--query", "query_path", type=click.Path(path_type=Path), default=None,
              help="Cross-session run: the query session (docs/cross-session.md).")
@click.option("--database", "database_path", type=click.Path(path_type=Path), default=None,
              help="Cross-session run: the database session.")
@click.option("--align", "align_path", type=click.Path(path_type=Path, dir_okay=False),
              default=None, help="Rigid transform (12 or 16 numbers) moving the query "
                                 "session's LiDAR poses into the database's world frame.")
@click.option("--pairs", "pairs_text", default=None, metavar="FILE|ssc[:N]",
              help="Score a list of pairs instead of protocols 1/2: a file of 'i j label' "
                   "lines, or 'ssc' / 'ssc:N' for SSC's rule (< 3 m and more than 50 frames "
                   "apart; N negatives > 20 m per positive, default 10, seed 0).")
@click.option("--loops", "loop_paths", multiple=True,
              type=click.Path(path_type=Path, dir_okay=False),
              help="Score this file's loops (g2o, matches.csv, pair list; docs/loops.md) "
                   "instead of a descriptor; may be repeated.")
@click.option("--loops-format",
              type=click.Choice(["g2o", "matches", "liris-txt", "pairs", "tum", "mapclosures"]),
              default=None, help="Format of every --loops file [default: detected].")
@click.option("--loops-index-base", type=click.IntRange(0, 1), default=0, show_default=True,
              help="Pair lists: 0- or 1-based frame indices.")
@click.option("--loops-gap", type=click.IntRange(min=1), default=1, show_default=True,
              help="g2o: an edge is a loop when its vertex ids differ by more than this.")
@loops_options
@click.option("--convention-band", is_flag=True,
              help="Also score protocol 1 under every convention preset that applies to the "
                   "run (same pose frame), from the same matching pass: each metric's value "
                   "under the run's convention and its min-max over the presets.")
@click.option("--ranking", is_flag=True,
              help="Also rank each query's database (Recall@1..25, Recall@1 %, MRR) in a "
                   "within-sequence run: one more matching pass for protocol 1.")
@descriptor_options
@ground_truth_options
@click.option("--recall-denominator", type=click.Choice(["revisits", "accepted"]),
              default="revisits", show_default=True,
              help="Protocol 1 recall: TP / revisit queries, or Scan Context's accepted-only FN.")
@click.option("--candidates", type=int, default=None,
              help="Retrieval depth K: protocol 1 through the descriptor's retrieval stage "
                   "(global descriptors), or K of two-stage methods [default: the method's].")
@click.option("--export-loops", "export_path", type=click.Path(path_type=Path), default=None,
              help="Write protocol 1's accepted loops at the F1max threshold: FILE.g2o (a "
                   "pose graph: VERTEX_SE3:QUAT per frame, EDGE_SE3:QUAT per loop), FILE.tum "
                   "(t_i t_j x y z qx qy qz qw) or FILE.txt (i j x y z qx qy qz qw); "
                   "docs/loop-poses.md.")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Run folder [default: results/<sequence>-<timestamp>].")
@click.option("--overwrite", is_flag=True,
              help="Replace an existing run folder liris wrote (never an input or a folder "
                   "holding other files), and existing --export-loops files.")
@click.option("--block-pairs", type=int, default=DEFAULT_PAIR_BUDGET, show_default=True,
              help="Distances computed per block (bounds memory).")
@click.option("--json", "as_json", is_flag=True, help="Print metrics.json instead of a table.")
@click.option("--plan", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="YAML list of sequences x descriptors x protocols, all evaluated into one "
                   "run folder with a summary table (see lidar_iris_eval/runs/plan.py).")
@click.option("--scheduler", default="processes", show_default=True,
              help="processes (a local pool of --workers), local (a Dask LocalCluster of "
                   "--workers) or tcp://HOST:PORT (an existing Dask cluster).")
def command(**options) -> None:
    """Evaluate descriptors on SEQUENCE with protocol 1 and/or 2.

    Descriptors are extracted first when the cache lacks them. Results go to a
    run folder (docs/results-format.md) that `liris plot` reads.
    """
    request = build_request(**options)
    MODE_RUNNERS[mode_of(request)](request)


def build_request(*, sequence, protocols, query_path, database_path, align_path, pairs_text,
                  loop_paths, loops_format, loops_index_base, loops_gap, convention_band,
                  ranking, descriptor_text, preset, params, sensor, cache_dir, workers, quiet,
                  candidates, export_path, out, overwrite, block_pairs, as_json,
                  reader_options, plan, scheduler, loop_settings, odometry, odometry_path,
                  seeds, loop_extra, **conventions) -> EvalRequest:
    """The :class:`EvalRequest` of this call's options.

    ``conventions`` are the ground-truth options (``radius``, ``exclude``, ...):
    :func:`~lidar_iris_eval.cli.options.ground_truth_options` has already
    resolved them into the running command's convention, so they are read
    from there, not again.
    """
    conv = current_convention()  # every ground-truth rule, validated once (Settings)
    externals, external_metric = external_options()
    return EvalRequest(
        convention=conv, settings=conv.replace(candidates=candidates, pair_budget=block_pairs),
        sequences=tuple(sequence), protocols=tuple(protocols), descriptor_text=descriptor_text,
        preset=preset, params=tuple(params), sensor=sensor, reader_options=reader_options,
        cache_dir=cache_dir, workers=workers, scheduler=scheduler, quiet=quiet, out=out,
        overwrite=overwrite, as_json=as_json, fmt=table_format(), plan=plan, query=query_path,
        database=database_path, align=align_path, pairs_text=pairs_text,
        loop_paths=tuple(loop_paths), loops_format=loops_format,
        loops_index_base=loops_index_base, loops_gap=loops_gap, loop_extra=loop_extra,
        convention_band=convention_band, ranking=ranking, export_path=export_path,
        loop_settings=loop_settings, odometry=odometry, odometry_path=odometry_path,
        seeds=seeds, externals=externals, external_metric=external_metric,
        command_extra=config_extra(conv))


def mode_of(request: EvalRequest) -> str:
    """The mode of :data:`MODE_RUNNERS` a request asks for.

    The order is the precedence of the options: any of ``--query``,
    ``--database`` or ``--align`` makes a cross-session run (which then refuses
    a SEQUENCE or a plan); a plan file without a SEQUENCE that lists
    query/database pairs is a plan of sessions; ``--loops`` scores loop files;
    a plan or not exactly one SEQUENCE is a run of many sequences; ``--pairs``
    scores a pair list; the rest is one sequence.
    """
    if not request.within:
        return "sessions"
    if request.plan is not None and not request.sequences and is_sessions_plan(request.plan):
        return "sessions-plan"
    if request.loop_paths:
        return "loops"
    if request.plan is not None or len(request.sequences) != 1:
        return "many"
    if request.pairs_text is not None:
        return "pairs"
    return "sequence"


#: each mode of ``liris eval``: a function of the request that checks what it needs
MODE_RUNNERS = {"sequence": run_sequence, "many": run_many, "sessions": run_sessions,
                "sessions-plan": run_sessions_plan, "pairs": run_pairs, "loops": run_loops}


__all__ = ["MODE_RUNNERS", "build_request", "command", "loop_export_paths", "mode_of"]
