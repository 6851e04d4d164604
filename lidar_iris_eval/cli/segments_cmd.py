"""``liris segments SEQUENCE``: the segmentation report of ESM's local maps (issue 34).

Parses the options, calls :func:`lidar_iris_eval.evaluation.segment_report.segment_report`
once per ``--preset`` and prints :func:`report_lines`; the JSON and the figure
(:mod:`lidar_iris_eval.plotting.segment_report`) are optional.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from lidar_iris_eval.cli.output import check_output_file, write_output_file
from lidar_iris_eval.cli.sequence_options import pose_file_options, sequence_options
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.ownership import check_new_files


def _overrides(items: tuple[str, ...]) -> dict:
    import yaml

    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise LirisError(f"--param {item}", "expected KEY=VALUE, e.g. radius=0.3")
        try:
            out[key.strip()] = yaml.safe_load(text)
        except yaml.YAMLError:
            raise LirisError(f"--param {item}", "value is not valid YAML") from None
    return out


@click.command("segments")
@click.argument("sequence", type=click.Path(path_type=Path))
@sequence_options
@pose_file_options
@click.option("--preset", "presets", multiple=True,
              help="An ESM local-map preset (repeatable: one report each, side by side) "
                   "[default: local-maps].")
@click.option("--param", "params", multiple=True, metavar="KEY=VALUE",
              help="An ESM parameter for every preset (repeatable), e.g. radius=0.3.")
@click.option("--exclude", type=int, default=30, show_default=True,
              help="E (frames): the local-map window and the revisit gap.")
@click.option("--radius", type=float, default=4.0, show_default=True,
              help="Revisit radius (m) of the loop queries.")
@click.option("--match", type=float, default=1.0, show_default=True,
              help="Two segments are the same when their world centroids are this close (m).")
@click.option("--gap", type=int, default=0, show_default=True,
              help="Frames between the two maps of the neighbour repeatability (0: W).")
@click.option("--limit", type=int, default=None, help="Only the first N frames.")
@click.option("--name", default=None, help="The sequence's name in the report [its path].")
@click.option("--json-out", "json_path", type=click.Path(path_type=Path), default=None,
              help="Write the reports (a list) as JSON to FILE.")
@click.option("--figure", "figure_path", type=click.Path(path_type=Path), default=None,
              help="Write the side-by-side figure to FILE (.png, .pdf or .svg).")
@click.option("--with-json", "with_json", multiple=True, type=click.Path(path_type=Path),
              help="Reports of earlier runs (their --json-out) drawn in the same figure.")
@click.option("--overwrite", is_flag=True, help="Replace an existing --json-out / --figure.")
def command(sequence, reader_options, presets, params, exclude, radius, match, gap, limit,
            name, json_path, figure_path, with_json, overwrite):
    """Segments per local map, their repeatability at neighbours and revisits, and the
    retrieval rank of the true target, for a sequence with poses (ESM local maps)."""
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.evaluation.segment_report import report_lines, segment_report
    from lidar_iris_eval.io import open_sequence

    if exclude < 1:
        raise LirisError(f"--exclude {exclude}", "must be at least 1 frame")
    for flag, value in (("--radius", radius), ("--match", match)):
        if not value > 0:
            raise LirisError(f"{flag} {value}", "must be positive")
    if json_path is not None:
        check_output_file(json_path, "--json-out")
    if figure_path is not None:
        check_output_file(figure_path, "--figure")
        if figure_path.suffix.lower() not in (".png", ".pdf", ".svg"):
            raise LirisError(f"--figure {figure_path}", "give a .png, .pdf or .svg file")
    # the shared rule for single output files: an existing one only with --overwrite, never
    # a file of the input sequence (it was replaced without a word)
    check_new_files([p for p in (json_path, figure_path) if p is not None], overwrite,
                    "--json-out/--figure", inputs=[sequence, *with_json])
    earlier = []
    for path in with_json:
        try:
            loaded = json.loads(Path(path).read_text())
        except (OSError, ValueError) as err:
            raise LirisError(f"--with-json {path}", f"cannot read a report ({err})") from None
        earlier.extend(loaded if isinstance(loaded, list) else [loaded])
    overrides = _overrides(params)
    descriptors = [get_descriptor("esm", p, **overrides) for p in (presets or ("local-maps",))]
    for d in descriptors:
        if not d.local_map:
            raise LirisError(f"--preset {d.preset}", "is not a local-map preset")
    seq = open_sequence(sequence, **reader_options)
    if getattr(seq, "poses", None) is None:
        raise LirisError(sequence, "has no poses; the report needs them (give --poses)")
    reports = []
    for d in descriptors:
        def progress(k, n, label=d.preset):
            if k % 50 == 0 or k == n:
                click.echo(f"  {label}: {k}/{n} frames", err=True)

        report = segment_report(seq, d, exclude, name=name or str(sequence), radius=radius,
                                match=match, gap=gap, limit=limit,
                                progress=progress if sys.stderr.isatty() else None)
        reports.append(report)
        for line in report_lines(report):
            click.echo(line)
    if json_path is not None:
        write_output_file(json_path, json.dumps(reports, indent=1) + "\n")
    if figure_path is not None:
        from lidar_iris_eval.plotting.segment_report import plot_segment_reports

        plot_segment_reports(earlier + reports, figure_path)
