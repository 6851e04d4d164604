"""``liris datasets``: the registered dataset readers and the layout each expects."""

from __future__ import annotations

import click

from lidar_iris_eval.cli.output import echo_json


@click.command("datasets")
@click.option("--json", "as_json", is_flag=True, help="Print the registry as JSON.")
def command(as_json):
    """List the dataset readers: the path to give, its pose frame, what liris converts,
    the scans' frame (every reader returns z-up scans) and what it gives as intensity.

    A SEQUENCE is detected from its folder; --dataset NAME (on every command that
    opens a sequence) forces a reader. Formats: docs/datasets.md.
    """
    from lidar_iris_eval.io.datasets import all_datasets

    DATASETS = all_datasets(strict=False)  # with the external readers (lidar_iris_eval/plugins.py)

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
