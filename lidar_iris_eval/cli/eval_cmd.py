"""``liris eval``: protocol 1 and/or 2 for one or more descriptors, written to a run folder.

Parsing, printing and writing only: the evaluation itself is
:func:`lidar_iris_eval.evaluation.evaluate.evaluate`.
"""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.cache import DescriptorCache, default_cache_dir
from lidar_iris_eval.cli.descriptor_options import build_descriptors, descriptor_options, open_input
from lidar_iris_eval.cli.loop_options import (
    check_odometry_file,
    loop_pose_options,
    read_odometry,
)
from lidar_iris_eval.cli.loops_eval import loops_options
from lidar_iris_eval.cli.options import current_convention, ground_truth_options
from lidar_iris_eval.cli.output import echo_json
from lidar_iris_eval.cli.workflow import (
    config_extra,
    externals_for,
    extract_all,
    table_format,
    workflow_options,
)
from lidar_iris_eval.errors import LirisError, register_flags
from lidar_iris_eval.evaluation.evaluate import (
    bind_exclusion,
    check_request,
    evaluate,
    export_loops,
    loop_export_paths,
)
from lidar_iris_eval.executor import check_scheduler, open_executor
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET
from lidar_iris_eval.ownership import check_new_files
from lidar_iris_eval.runs.table import render_band_table, render_table
from lidar_iris_eval.runs.writer import check_run_dir, default_run_dir, json_ready, write_run
from lidar_iris_eval.sensors import resolve_sensor

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
def command(sequence, protocols, query_path, database_path, align_path, pairs_text, loop_paths,
            loops_format, loops_index_base, loops_gap, convention_band, ranking,
            descriptor_text, preset, params, sensor, cache_dir, workers,
            quiet, radius, exclude, distance, pose_frame, recall_denominator, candidates,
            export_path, out, overwrite, block_pairs, as_json, reader_options, plan, scheduler,
            loop_settings, odometry, odometry_path, seeds, loop_extra):
    """Evaluate descriptors on SEQUENCE with protocol 1 and/or 2.

    Descriptors are extracted first when the cache lacks them. Results go to a
    run folder (docs/results-format.md) that `liris plot` reads.
    """
    conv = current_convention()  # every ground-truth rule, validated once (Settings)
    if workers < 1:
        raise LirisError(f"--workers {workers}", "must be at least 1")
    settings = conv.replace(candidates=candidates, pair_budget=block_pairs)
    within = query_path is None and database_path is None and align_path is None
    single = within and plan is None and len(sequence) == 1 and not loop_paths \
        and pairs_text is None and seeds is None
    if convention_band and not single:
        raise LirisError("--convention-band", "applies to one within-sequence run of "
                         "descriptors (no --query/--database, --plan, --loops, --pairs, --seeds)")
    if not within:
        _within_sequence_odometry(odometry)
        from lidar_iris_eval.cli.sessions_eval import evaluate_sessions_cli

        evaluate_sessions_cli(sequence, query_path, database_path, align_path, protocols,
                              descriptor_text, preset, params, sensor, cache_dir, workers, quiet,
                              settings, conv, out, overwrite, as_json, reader_options, plan,
                              export_path, scheduler)
        return
    if plan is not None and not sequence:
        from lidar_iris_eval.cli.sessions_plan import is_sessions_plan, run_sessions_plan

        if is_sessions_plan(plan):  # query/database pairs
            _within_sequence_odometry(odometry)
            if protocols:
                raise LirisError("--protocol", "does not apply to a plan of query/database "
                                               "pairs")
            run_sessions_plan(plan, descriptor_text, preset, params, sensor, cache_dir, workers,
                              quiet, settings, conv, out, overwrite, reader_options, scheduler)
            return
    if loop_paths and (plan is not None or len(sequence) > 1):
        raise LirisError("--loops", "scores one sequence (a SEQUENCE or --poses)")
    if loop_paths and len(sequence) <= 1 and plan is None:  # poses alone are enough
        from lidar_iris_eval.cli.loops_eval import evaluate_loops_cli, open_loops_sequence

        evaluate_loops_cli(open_loops_sequence(sequence[0] if sequence else None,
                                               reader_options),
                           loop_paths, loops_format, loops_index_base, loops_gap, settings,
                           protocols, descriptor_text, out, overwrite, as_json,
                           {**config_extra(conv), "reader_options": reader_options}, loop_extra)
        return
    if plan is not None or len(sequence) != 1:  # several sequences: one folder, a summary
        if loop_settings.registers or odometry_path is not None or seeds is not None:
            raise LirisError("--refine/--gt-pose/--odometry/--seeds",
                             "apply to a single sequence only")
        _evaluate_many(sequence, plan, protocols, descriptor_text, preset, params, sensor,
                       cache_dir, workers, quiet, settings, conv, out, overwrite, export_path,
                       as_json, reader_options, scheduler, odometry)
        return
    sequence = sequence[0]
    sensor = resolve_sensor(sensor, lambda: open_input(sequence, reader_options))
    descriptors = build_descriptors(descriptor_text, preset, sensor, params, odometry) \
        if descriptor_text else []
    check_odometry_file(odometry_path, descriptors)
    if pairs_text is not None:
        from lidar_iris_eval.cli.pairs_eval import evaluate_pairs_cli

        seq = open_input(sequence, reader_options)
        for d in descriptors:
            d.check_inputs(seq)
        with open_executor(check_scheduler(scheduler), workers) as executor:
            evaluate_pairs_cli(seq, descriptors, pairs_text, protocols, cache_dir, workers,
                               quiet, out, overwrite, as_json, executor,
                               {**config_extra(conv), "sensor": sensor,
                                "odometry": odometry})
        return
    check_request(descriptors, protocols, settings)
    if export_path is not None:
        if "1" not in protocols:
            raise LirisError(f"--export-loops {export_path}", "needs --protocol 1")
        if export_path.suffix.lower() not in (".g2o", ".tum", ".txt"):
            raise LirisError(f"--export-loops {export_path}",
                             "use a .g2o, .tum or .txt file name")
    seq = open_input(sequence, reader_options)
    descriptors += externals_for(seq)  # --external NAME=PATH
    descriptors = bind_exclusion(descriptors, settings.exclude)  # local maps: window = E
    check_request(descriptors, protocols, settings)
    for d in descriptors:
        d.check_inputs(seq)
    vertices = read_odometry(odometry_path, seq) if odometry_path is not None else None
    if out is None:
        out = default_run_dir(seq.name)
    check_run_dir(out, overwrite)
    if export_path is not None:
        check_new_files(loop_export_paths(export_path, [d.name for d in descriptors]),
                        overwrite, "--export-loops", inputs=[sequence])

    cache = DescriptorCache(cache_dir if cache_dir is not None else default_cache_dir())
    with open_executor(check_scheduler(scheduler), workers) as executor:
        def run_once(descs):
            return evaluate(seq, descs, protocols, settings, cache=cache, workers=workers,
                            progress=not quiet, executor=executor, loop_settings=loop_settings,
                            ranking=ranking, convention_band=convention_band,
                            dbs=extract_all(seq, descs, cache, workers, quiet, executor))

        if seeds is None:
            run = run_once(descriptors)
        else:  # issue 23: stochastic stages once per seed, mean and range in each row
            from lidar_iris_eval.evaluation.seeds import evaluate_seeds

            run = evaluate_seeds(run_once, descriptors, seeds)
        engine_info = (executor.describe() if executor.distributes_blocks
                       else {"scheduler": scheduler})
    extra = {**config_extra(conv), "engine": engine_info, "odometry": odometry,
             **({"odometry_file": str(odometry_path)} if odometry_path is not None else {}),
             **({"seeds": list(seeds)} if seeds is not None else {})}
    write_run(run, out, overwrite, sensor=sensor, reader_options=reader_options, **extra)
    if export_path is not None and odometry != "gt":  # the .g2o vertices: the same odometry
        from lidar_iris_eval.localmaps.odometry import estimate_odometry

        vertices = estimate_odometry(seq, odometry, progress=not quiet).poses
    exported = export_loops(run, export_path, vertices) if export_path is not None else {}
    if as_json:
        echo_json(json_ready({**run.header(run.config(sensor=sensor,
                                                      reader_options=reader_options, **extra)),
                              "results": run.rows}))
        return
    click.echo(render_table(run.rows, table_format()))
    band = render_band_table(run.rows, table_format())
    if band:
        click.echo(band, err=table_format() != "table")
    click.echo(  # after a Markdown/LaTeX/CSV table, to stderr: the table stays pasteable
        f"conventions: radius {settings.radius:g} m, exclude "
        + (f"E={settings.exclude} ({settings.exclude_name})" if settings.exclude_seconds is None
           else f"{conv.exclude_seconds:g} s by scan time")
        + f", {settings.distance} distance, {run.pose_frame}-frame poses, "
        f"protocol 1 recall denominator '{settings.recall_denominator}', convention "
        f"{conv.name}; results in {out}", err=table_format() != "table")
    print_loop_poses(run, loop_settings)
    for name, (path, count) in exported.items():
        click.echo(f"{name}: {count} accepted loops written to {path}")


def print_loop_poses(run, loop_settings) -> None:
    """The loop-pose table (registration recall, refined errors, registration time), and
    one n/a line per method that has no point clouds to register."""
    from lidar_iris_eval.runs.loop_table import render_loop_table, render_seed_table

    for text in (render_loop_table(run.rows, table_format()),
                 render_seed_table(run.rows, table_format())):
        if text:
            click.echo(text, err=table_format() != "table")
    for row in run.rows:
        for key in ("refine_note", "gt_pose_note"):
            if row.get(key):
                click.echo(f"{row['descriptor']}: {row[key]}")


def _within_sequence_odometry(odometry: str) -> None:
    """Refuse an estimated odometry where local maps are not built (cross-session runs)."""
    if odometry != "gt":
        raise LirisError(f"--odometry {odometry}", "applies to within-sequence runs (a "
                                                  "SEQUENCE or a plan of sequences)")


def _evaluate_many(sequences, plan, protocols, descriptor_text, preset, params, sensor,
                   cache_dir, workers, quiet, settings, conv, out, overwrite, export_path,
                   as_json, reader_options, scheduler, odometry: str = "gt") -> None:
    """SEQUENCE... or --plan: :func:`lidar_iris_eval.cli.eval_many.evaluate_many`."""
    from lidar_iris_eval.cli.eval_many import evaluate_many
    from lidar_iris_eval.runs.plan import read_plan, runs_from_sequences

    if plan is not None and sequences:
        raise LirisError("--plan", "give either sequences or --plan FILE, not both")
    if plan is None and not sequences:
        raise LirisError("SEQUENCE", "give a sequence, several, or --plan FILE")
    if export_path is not None or as_json:
        raise LirisError("--export-loops/--json", "apply to a single sequence only")
    runs = (read_plan(plan, descriptor_text, protocols) if plan is not None
            else runs_from_sequences(sequences, descriptor_text, protocols))
    cache = DescriptorCache(cache_dir if cache_dir is not None else default_cache_dir())
    evaluate_many(runs, settings=settings, conv=conv, cache=cache, workers=workers, quiet=quiet,
                  preset=preset, sensor=sensor, params=params, reader_options=reader_options,
                  scheduler=scheduler, out=out, overwrite=overwrite, odometry=odometry)


__all__ = ["command", "loop_export_paths"]
