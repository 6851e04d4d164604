"""``liris eval``: protocol 1 and/or 2 for one or more descriptors, written to a run folder.

Parsing, printing and writing only: the evaluation itself is
:func:`lidar_iris_eval.evaluation.evaluate.evaluate`.
"""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.cache import DescriptorCache, default_cache_dir
from lidar_iris_eval.cli.descriptor_options import build_descriptors, descriptor_options, open_input
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
    check_request,
    evaluate,
    export_loops,
    loop_export_paths,
    write_run,
)
from lidar_iris_eval.evaluation.report import check_run_dir, default_run_dir, json_ready
from lidar_iris_eval.executor import check_scheduler, open_executor
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET
from lidar_iris_eval.runs.table import render_table
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
@click.argument("sequence", nargs=-1, type=click.Path(path_type=Path))
@click.option("--protocol", "protocols", type=click.Choice(["1", "2"]), multiple=True,
              required=True, help="1 (best match per query) or 2 (all pairs); may be repeated.")
@descriptor_options
@ground_truth_options
@click.option("--recall-denominator", type=click.Choice(["revisits", "accepted"]),
              default="revisits", show_default=True,
              help="Protocol 1 recall: TP / revisit queries, or Scan Context's accepted-only FN.")
@click.option("--candidates", type=int, default=None,
              help="Retrieval depth K: protocol 1 through the descriptor's retrieval stage "
                   "(global descriptors), or K of two-stage methods [default: the method's].")
@click.option("--export-loops", "export_path", type=click.Path(path_type=Path), default=None,
              help="Write protocol 1's accepted loops at the F1max threshold as pose-graph "
                   "edges: FILE.g2o (EDGE_SE3:QUAT) or FILE.txt (i j x y z qx qy qz qw).")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Run folder [default: results/<sequence>-<timestamp>].")
@click.option("--overwrite", is_flag=True, help="Replace an existing run folder.")
@click.option("--block-pairs", type=int, default=DEFAULT_PAIR_BUDGET, show_default=True,
              help="Distances computed per block (bounds memory).")
@click.option("--json", "as_json", is_flag=True, help="Print metrics.json instead of a table.")
@click.option("--plan", type=click.Path(path_type=Path, dir_okay=False), default=None,
              help="YAML list of sequences x descriptors x protocols, all evaluated into one "
                   "run folder with a summary table (see lidar_iris_eval/engine/plan.py).")
@click.option("--scheduler", default="processes", show_default=True,
              help="processes (a local pool of --workers), local (a Dask LocalCluster of "
                   "--workers) or tcp://HOST:PORT (an existing Dask cluster).")
def command(sequence, protocols, descriptor_text, preset, params, sensor, cache_dir, workers,
            quiet, radius, exclude, distance, pose_frame, recall_denominator, candidates,
            export_path, out, overwrite, block_pairs, as_json, reader_options, plan, scheduler):
    """Evaluate descriptors on SEQUENCE with protocol 1 and/or 2.

    Descriptors are extracted first when the cache lacks them. Results go to a
    run folder (docs/results-format.md) that `liris plot` reads.
    """
    conv = current_convention()  # every ground-truth rule, validated once (Settings)
    if workers < 1:
        raise LirisError(f"--workers {workers}", "must be at least 1")
    settings = conv.replace(candidates=candidates, pair_budget=block_pairs)
    if plan is not None or len(sequence) != 1:  # several sequences: one folder, a summary
        _evaluate_many(sequence, plan, protocols, descriptor_text, preset, params, sensor,
                       cache_dir, workers, quiet, settings, conv, out, overwrite, export_path,
                       as_json, reader_options, scheduler)
        return
    sequence = sequence[0]
    sensor = resolve_sensor(sensor, lambda: open_input(sequence, reader_options))
    descriptors = build_descriptors(descriptor_text, preset, sensor, params) \
        if descriptor_text else []
    check_request(descriptors, protocols, settings)
    if export_path is not None:
        if "1" not in protocols:
            raise LirisError(f"--export-loops {export_path}", "needs --protocol 1")
        if export_path.suffix.lower() not in (".g2o", ".txt"):
            raise LirisError(f"--export-loops {export_path}", "use a .g2o or .txt file name")
    seq = open_input(sequence, reader_options)
    descriptors += externals_for(seq)  # --external NAME=PATH
    check_request(descriptors, protocols, settings)
    for d in descriptors:
        d.check_inputs(seq)
    if out is None:
        out = default_run_dir(seq.name)
    check_run_dir(out, overwrite)

    cache = DescriptorCache(cache_dir if cache_dir is not None else default_cache_dir())
    with open_executor(check_scheduler(scheduler), workers) as executor:
        run = evaluate(seq, descriptors, protocols, settings, cache=cache, workers=workers,
                       progress=not quiet, executor=executor,
                       dbs=extract_all(seq, descriptors, cache, workers, quiet, executor))
        engine_info = (executor.describe() if executor.distributes_blocks
                       else {"scheduler": scheduler})
    extra = {**config_extra(conv), "engine": engine_info}
    write_run(run, out, overwrite, sensor=sensor, reader_options=reader_options, **extra)
    exported = export_loops(run, export_path) if export_path is not None else {}
    if as_json:
        echo_json(json_ready({**run.header(run.config(sensor=sensor,
                                                      reader_options=reader_options, **extra)),
                              "results": run.rows}))
        return
    click.echo(render_table(run.rows, table_format()))
    click.echo(  # after a Markdown/LaTeX/CSV table, to stderr: the table stays pasteable
        f"conventions: radius {settings.radius:g} m, exclude "
        + (f"E={settings.exclude} ({settings.exclude_name})" if settings.exclude_seconds is None
           else f"{conv.exclude_seconds:g} s by scan time")
        + f", {settings.distance} distance, {run.pose_frame}-frame poses, "
        f"protocol 1 recall denominator '{settings.recall_denominator}', convention "
        f"{conv.name}; results in {out}", err=table_format() != "table")
    for name, (path, count) in exported.items():
        click.echo(f"{name}: {count} accepted loops written to {path}")


def _evaluate_many(sequences, plan, protocols, descriptor_text, preset, params, sensor,
                   cache_dir, workers, quiet, settings, conv, out, overwrite, export_path,
                   as_json, reader_options, scheduler) -> None:
    """SEQUENCE... or --plan: :func:`lidar_iris_eval.cli.eval_many.evaluate_many`."""
    from lidar_iris_eval.cli.eval_many import evaluate_many
    from lidar_iris_eval.engine.plan import read_plan, runs_from_sequences

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
                  scheduler=scheduler, out=out, overwrite=overwrite)


__all__ = ["command", "loop_export_paths"]
