"""``liris eval SEQUENCE --loops FILE``: score other systems' loops (docs/loops.md)."""

from __future__ import annotations

import click

from lidar_iris_eval.cli.output import echo_json
from lidar_iris_eval.cli.workflow import table_format
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.runs.table import render_table
from lidar_iris_eval.runs.writer import check_run_dir, default_run_dir, json_ready, write_run


def evaluate_loops_cli(seq, loop_paths, loop_format, index_base, gap, settings, protocols,
                       descriptor_text, out, overwrite, as_json, extra) -> None:
    """Score, write and print a loops run."""
    from lidar_iris_eval.evaluation.external_loops import evaluate_loops

    if descriptor_text:
        raise LirisError("--loops", "score loop files or descriptors, not both in one run")
    if protocols and tuple(protocols) != ("1",):
        raise LirisError("--protocol", "loops are scored by protocol 1 only")
    if out is None:
        out = default_run_dir(f"{seq.name}-loops")
    check_run_dir(out, overwrite)
    run = evaluate_loops(seq, list(loop_paths), settings, formats=loop_format,
                         index_base=index_base, gap=gap)
    write_run(run, out, overwrite, **extra)
    if as_json:
        echo_json(json_ready({**run.header(run.config(**extra)), "results": run.rows}))
        return
    click.echo(render_table(run.rows, table_format()))
    for row in run.rows:
        click.echo(f"{row['descriptor']}: {row['n_loops']} loops, {row['loops_tp']} TP / "
                   f"{row['loops_fp']} FP, revisit coverage "
                   f"{row['revisit_coverage'] if row['revisit_coverage'] is not None else 'n/a'}"
                   f"; results in {out}", err=table_format() != "table")
