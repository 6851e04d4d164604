"""``liris report RUN``: one offline HTML page for a run folder (needs the ``report`` extra)."""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.report_html.page import DEFAULT_FAILURES, MAX_AFFINITY_PX


@click.command("report")
@click.argument("run", type=click.Path(path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Report folder [default: RUN/report].")
@click.option("--overwrite", is_flag=True, help="Replace an existing report folder.")
@click.option("--max-affinity-px", type=click.IntRange(min=16), default=MAX_AFFINITY_PX,
              show_default=True, help="Largest side of an embedded affinity image.")
@click.option("--failures", type=click.IntRange(min=0), default=DEFAULT_FAILURES,
              show_default=True, metavar="N",
              help="Failure atlas: per method the N most confident false positives and the N "
                   "worst-missed revisits (0: no atlas section; needs the run's scans).")
def command(run, out, overwrite, max_affinity_px, failures):
    """Write an HTML page for RUN: interactive PR curves, affinity images, the
    trajectory with TP/FP/missed markers, the metrics table, the conventions,
    the convention band (runs made with --convention-band) and the failure atlas.

    The page works offline: plotly's JavaScript is written beside it. Needs
    plotly (pip install 'lidar_iris_eval[report]').
    """
    from lidar_iris_eval.report_html import build_report

    page = build_report(run, out, overwrite, max_affinity_px, failures)
    click.echo(f"report: {page}")
