"""``liris datasets``: the registered dataset readers, and ``datasets check SEQ``."""

from __future__ import annotations

from pathlib import Path

import click

from lidar_iris_eval.cli.output import check_output_file, echo_json, echo_table, format_value
from lidar_iris_eval.cli.sequence_options import sequence_options


@click.group("datasets", invoke_without_command=True)
@click.option("--json", "as_json", is_flag=True, help="Print the registry as JSON.")
@click.pass_context
def command(ctx, as_json):
    """List the dataset readers: the path to give, its pose frame, what liris converts,
    the scans' frame (every reader returns z-up scans) and what it gives as intensity.

    A SEQUENCE is detected from its folder; --dataset NAME (on every command that
    opens a sequence) forces a reader. Formats: docs/datasets.md. `liris datasets
    check SEQ` checks a sequence's times and poses before you trust it.
    """
    if ctx.invoked_subcommand is not None:
        return
    from lidar_iris_eval.io.datasets import DATASETS

    if as_json:
        echo_json([{"name": s.name, "title": s.title, "layout": s.layout,
                    "pose_frame": s.pose_frame, "converts": s.converts, "sensor": s.sensor,
                    "frame": s.frame, "intensity": s.intensity,
                    "detected_by": s.looks_for, "generic": s.generic}
                   for s in DATASETS.values()])
        return
    width = max(len(s.name) for s in DATASETS.values())
    for spec in DATASETS.values():
        sensor = spec.sensor or "none (--sensor auto guesses)"
        click.echo(f"{spec.name.ljust(width)}  {spec.title}  [--sensor {sensor}]")
        pad = " " * (width + 2)
        click.echo(f"{pad}layout: {spec.layout}")
        click.echo(f"{pad}poses:  {spec.pose_frame}")
        click.echo(f"{pad}liris:  {spec.converts}")
        click.echo(f"{pad}frame:  {spec.frame}")
        click.echo(f"{pad}intensity: {spec.intensity}")


@command.command("check")
@click.argument("sequence", required=False, type=click.Path(path_type=Path))
@click.option("--poses", "poses_path", type=click.Path(path_type=Path),
              help="Pose file (overrides the sequence's, or alone without SEQUENCE).")
@click.option("--calib", "calib_path", type=click.Path(path_type=Path),
              help="KITTI calib.txt with Tr (camera poses to LiDAR poses).")
@sequence_options
@click.option("--platform", type=click.Choice(["car", "robot", "handheld"]), default="car",
              show_default=True,
              help="Speed and yaw-rate limits: car 40 m/s, 120 deg/s; robot 5 m/s, 180 deg/s; "
                   "handheld 5 m/s, 360 deg/s (docs/datasets.md).")
@click.option("--max-speed", type=float, default=None, help="m/s; overrides the platform's.")
@click.option("--max-yaw-rate", type=float, default=None,
              help="deg/s; overrides the platform's.")
@click.option("--exclude", type=int, default=None,
              help="E (frames) for the pseudo-revisit count [30, the paper's].")
@click.option("--rate", type=float, default=None,
              help="Hz to assume when the input has no scan times (KITTI poses: 10).")
@click.option("--plot", "plot_out", type=click.Path(path_type=Path), default=None,
              help="Also draw the trajectory and the time steps with the findings marked.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --plot image.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def check(sequence, poses_path, calib_path, platform, max_speed, max_yaw_rate, exclude, rate,
          plot_out, overwrite, as_json, reader_options):
    """Check SEQUENCE before trusting it: time gaps between scans and between poses, pose
    rate vs scan rate, scans without poses and how they are matched, stationary spans and
    the pseudo-revisits they create at small E, ground-truth jumps (speed or yaw rate beyond
    the platform's limits) and duplicate stamps.
    """
    from lidar_iris_eval.atomic import figure_format
    from lidar_iris_eval.evaluation.sequence_check import check_timing, limits_for, timing_input
    from lidar_iris_eval.ownership import check_new_files

    limits = limits_for(platform, max_speed=max_speed, max_yaw_rate=max_yaw_rate,
                        exclude=exclude)
    if plot_out is not None:
        figure_format(plot_out, "--plot")
        check_output_file(plot_out, "--plot")
        check_new_files([plot_out], overwrite, "--plot",
                        inputs=[p for p in (sequence, poses_path, calib_path) if p is not None])
    data = timing_input(sequence, poses_path, calib_path, reader_options, rate)
    report = check_timing(data, limits)
    result = report.to_dict()
    if plot_out is not None:
        from lidar_iris_eval.plotting.sequence_check import plot_sequence_check

        result["plot"] = plot_sequence_check(data, report, plot_out)
    if as_json:
        echo_json(result)
        return
    for key, value in report.summary.items():
        click.echo(f"{key}: {format_value(value)}")
    click.echo("")
    echo_table([{"check": name, "findings": count, "status": "ok" if count == 0 else "FOUND"}
                for name, count in report.counts().items()])
    if report.findings:
        click.echo("")
        for finding in report.findings:
            click.echo(f"{finding['check']}: {finding['detail']}")
    else:
        click.echo("clean: no finding")
    if "plot" in result:
        click.echo(f"figure: {result['plot']}")
