"""``liris plot``: the paper's figures from one or more results directories."""

from __future__ import annotations

from pathlib import Path

import click


@click.command("plot")
@click.argument("results", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--compare", is_flag=True,
              help="Overlay the PR curves of several RESULTS directories.")
@click.option("--format", "fmt", type=click.Choice(["png", "pdf", "svg"]), default="png",
              show_default=True,
              help="File format (PNG at 300 dpi, always with a vector PDF copy).")
@click.option("--out", "out_dir", type=click.Path(path_type=Path),
              help="Output folder [default: RESULTS/figures; with --compare, "
                   "compare-<runs>/ next to the first run].")
@click.option("--frame", type=int, default=None,
              help="Frame for the LiDAR Iris figures [default: first revisit query].")
@click.option("--failures", type=int, default=None, metavar="N",
              help="Also the failure atlas: per method, the N most confident false positives "
                   "and the N worst-missed revisit queries (failures_<method>; needs the "
                   "run's scans).")
def command(results, compare, fmt, out_dir, frame, failures):
    """Write figures for RESULTS (a folder written by `liris eval`).

    One run gives pr_protocol1, pr_protocol2, affinity, trajectory, timing,
    iris_frame and iris_alignment (those whose inputs exist; the LiDAR Iris
    figures need the run's sequence on disk), and with --failures N the
    failure atlas failures_<method>. With --compare, two or more runs
    give pr_protocol1 and pr_protocol2 with one curve per run and method.

    Figures are derived outputs: files of the same name in the default output
    folder are replaced without asking; in an --out folder a warning names
    each file replaced.
    """
    from lidar_iris_eval.errors import LirisError
    from lidar_iris_eval.plotting import plot_compare, plot_run

    if compare:
        if frame is not None:
            raise LirisError("--frame", "applies to a single run, not --compare")
        if failures is not None:
            raise LirisError("--failures", "applies to a single run, not --compare")
        written = plot_compare(list(results), out_dir, fmt)
    else:
        if len(results) != 1:
            raise LirisError("liris plot", "give one RESULTS directory, or use --compare")
        written = plot_run(results[0], out_dir, fmt, frame=frame, failures=failures)
    for path in written:
        click.echo(str(path))
