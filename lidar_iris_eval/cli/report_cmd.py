"""``liris report RUN``: one offline HTML page for a run folder (needs the ``report`` extra)."""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.report_html.page import MAX_AFFINITY_PX


@click.command("report")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Report folder [default: RUN/report].")
@click.option("--overwrite", is_flag=True, help="Replace an existing report folder.")
@click.option("--max-affinity-px", type=click.IntRange(min=16), default=MAX_AFFINITY_PX,
              show_default=True, help="Largest side of an embedded affinity image.")
def command(run, out, overwrite, max_affinity_px):
    """Write an HTML page for RUN: interactive PR curves, affinity images, the
    trajectory with TP/FP/missed markers, the metrics table and the conventions.

    The page works offline: plotly's JavaScript is written beside it. Needs
    plotly (pip install 'lidar_iris_eval[report]').
    """
    from lidar_iris_eval.report_html import build_report

    page = build_report(run, out, overwrite, max_affinity_px)
    click.echo(f"report: {page}")
