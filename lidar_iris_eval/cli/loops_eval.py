"""``liris eval SEQUENCE --loops FILE``: score other systems' loops (docs/loops.md).

The sequence may be given by its poses alone: ``liris eval --poses POSES
[--times TIMES] --loops FILE`` (no scans are read to score loops).
"""

from __future__ import annotations

import functools

import click

from lidar_iris_eval.cli.eval_request import EvalRequest
from lidar_iris_eval.cli.output import echo_json
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.runs.table import render_table
from lidar_iris_eval.runs.writer import check_run_dir, default_run_dir, json_ready, write_run

#: reader options a pose-only sequence takes (the rest need scans)
POSE_ONLY_OPTIONS = ("poses", "times", "calib", "pose_format")


def loops_options(func):
    """Keyframe placement and pose-graph options of ``--loops`` (one keyword ``loop_extra``)."""

    @click.option("--loops-times", type=click.Path(dir_okay=False), default=None,
                  help="Keyframe k of a --loops file is the scan nearest this file's k-th "
                       "time (one time per line, e.g. SC-LIO-SAM's times.txt).")
    @click.option("--loops-map", type=click.Path(dir_okay=False), default=None,
                  help="Keyframe -> scan map of the --loops files: 'keyframe scan' lines.")
    @click.option("--loops-time-tolerance", type=click.FloatRange(min=0), default=0.05,
                  show_default=True, help="Seconds between a loop's time stamp and its scan.")
    @click.option("--loops-coverage-tolerance", type=click.IntRange(min=0), default=0,
                  show_default=True,
                  help="Frames: a true loop covers the revisit frames this close to its query.")
    @click.option("--loops-odometry", type=click.Path(dir_okay=False), default=None,
                  help="An odometry (KITTI or TUM, one LiDAR pose per scan) to build the "
                       "pose graph of files whose loops carry poses.")
    @click.option("--posegraph/--no-posegraph", default=None,
                  help="Optimise g2o graphs with all / true / no loops and report the APE "
                       "(gtsam) [default: when the graph has vertices and gtsam is installed].")
    @click.option("--posegraph-kernel", type=click.Choice(["none", "huber", "cauchy"]),
                  default="none", show_default=True,
                  help="Robust kernel on the loop edges of the pose-graph optimisation.")
    @click.option("--posegraph-kernel-k", type=click.FloatRange(min=0, min_open=True),
                  default=None, help="Kernel width (whitened units) [1.345].")
    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        kwargs["loop_extra"] = {
            "keyframe_times": kwargs.pop("loops_times"),
            "keyframe_map": kwargs.pop("loops_map"),
            "time_tolerance": kwargs.pop("loops_time_tolerance"),
            "coverage_tolerance": kwargs.pop("loops_coverage_tolerance"),
            "posegraph": kwargs.pop("posegraph"),
            "odometry": kwargs.pop("loops_odometry"),
            "kernel": kwargs.pop("posegraph_kernel"),
            "kernel_k": kwargs.pop("posegraph_kernel_k"),
        }
        return func(*args, **kwargs)

    return wrapper


def open_loops_sequence(sequence, reader_options: dict):
    """The SEQUENCE folder, or the sequence of ``--poses [--times] [--calib]`` alone."""
    if sequence is not None:
        from lidar_iris_eval.cli.descriptor_options import open_input

        return open_input(sequence, reader_options)
    if "poses" not in reader_options:
        raise LirisError("liris eval --loops", "give a SEQUENCE folder or --poses FILE")
    other = sorted(k for k in reader_options if k not in POSE_ONLY_OPTIONS)
    if other:
        from lidar_iris_eval.errors import options

        raise LirisError(options(other), "needs a SEQUENCE, not only --poses")
    from lidar_iris_eval.io.pose_sequence import open_pose_sequence

    return open_pose_sequence(reader_options["poses"], reader_options.get("times"),
                              reader_options.get("calib"),
                              reader_options.get("pose_format") or "auto")


def run_loops(req: EvalRequest) -> None:
    """Score, write and print a loops run (the mode ``loops``: one SEQUENCE or ``--poses``)."""
    from lidar_iris_eval.evaluation.external_loops import evaluate_loops, loop_scores

    req.refuse_convention_band()
    if req.plan is not None or len(req.sequences) > 1:
        raise LirisError("--loops", "scores one sequence (a SEQUENCE or --poses)")
    if req.descriptor_text:
        raise LirisError("--loops", "score loop files or descriptors, not both in one run")
    if req.protocols and tuple(req.protocols) != ("1",):
        raise LirisError("--protocol", "loops are scored by protocol 1 only")
    seq = open_loops_sequence(req.sequences[0] if req.sequences else None, req.reader_options)
    out, overwrite, fmt = req.out, req.overwrite, req.fmt
    extra = {**req.config_extra(), "reader_options": req.reader_options}
    if out is None:
        out = default_run_dir(f"{seq.name}-loops")
    check_run_dir(out, overwrite)
    run = evaluate_loops(seq, list(req.loop_paths), req.settings, formats=req.loops_format,
                         index_base=req.loops_index_base, gap=req.loops_gap, **req.loop_extra)
    write_run(run, out, overwrite, **extra)
    if req.as_json:
        echo_json(json_ready({**run.header(run.config(**extra)), "results": run.rows}))
        return
    click.echo(render_table(run.rows, fmt))
    err = fmt != "table"
    from lidar_iris_eval.runs.loop_table import render_loops_table

    click.echo(render_loops_table(run.rows, fmt), err=err)
    for row in run.rows:
        coverage = row["revisit_coverage"]
        click.echo(f"{row['descriptor']}: {row['n_loops']} loops, {row['loops_tp']} TP / "
                   f"{row['loops_fp']} FP, revisit coverage "
                   f"{f'{coverage:.4f}' if coverage is not None else 'n/a'} of revisit "
                   f"queries, {row['n_revisit_stretches_covered']} of "
                   f"{row['n_revisit_stretches']} revisit stretches; results in {out}",
                   err=err)
    for name, score in loop_scores(run).items():
        if score.damage is not None:
            click.echo(damage_text(name, score.damage), err=err)


def damage_text(name: str, damage) -> str:
    """The pose-graph damage table of one file, as text."""
    t = damage.table()
    lines = [f"{name}: pose graph ({damage.n_vertices} vertices, kernel {damage.kernel}), "
             "APE RMSE after SE(3) alignment:",
             f"  {'graph':<12} {'loops':>5} {'APE m':>9} {'added m':>9}"]
    for g, n, ape, added in zip(t["graph"], t["n_loops"], t["ape_rmse_m"], t["added_m"],
                                strict=True):
        added_text = "" if added != added else f"{added:+9.3f}"
        lines.append(f"  {g:<12} {n:>5} {ape:9.3f} {added_text:>9}")
    return "\n".join(lines)
