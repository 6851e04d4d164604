#!/usr/bin/env python
"""ESM training segments from any sequence liris reads (step 1 of training on real data).

    python scripts/esm_segments.py SEQUENCE -o SEGMENTS.npz [reader options]

SEQUENCE is opened exactly as ``liris eval`` opens it (KITTI layout, a PCD or
other scan folder with ``--poses`` / ``--times`` / ``--lidar-frame-poses``, a
dataset reader with ``--dataset``, a ROS bag; the same options). Every
frame's local map is built with the sequence's poses as ``liris eval -d
esm`` builds it (``--preset``, default ``local-maps``: its input filter and
front end; window W = ``--exclude``, 30), every ``--every-map``-th map (10) is
segmented, and each segment is stored with its world centroid. Positives for
training are views of the same segment in local maps at least W frames apart
(no shared scan) whose world centroids lie within ``--match`` m (1 m;
``dataset.SEQUENCE_MATCH``): the file tags each segment with its centroid
track (``dataset.sequence_local_map_segments``). Needs no torch; the file is
what ``scripts/train_esm.py --source segments`` reads (docs/esm.md,
"Training on real sequences").
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from lidar_iris_eval.cli import run_guarded
from lidar_iris_eval.cli.sequence_options import pose_file_options, sequence_options
from lidar_iris_eval.errors import LirisError


@click.command()
@click.argument("sequence", type=click.Path(path_type=Path))
@sequence_options
@pose_file_options
@click.option("-o", "--out", type=click.Path(path_type=Path), required=True,
              help="The segments file to write (.npz).")
@click.option("--overwrite", is_flag=True,
              help="Replace an existing --out file (never one inside SEQUENCE).")
@click.option("--preset", default="local-maps", show_default=True,
              help="The ESM local-map preset whose local maps and front end are used.")
@click.option("--exclude", type=int, default=30, show_default=True,
              help="W = E (frames): the local-map window; positives are >= W frames apart.")
@click.option("--every-map", "every_map", type=int, default=10, show_default=True,
              help="Segment every N-th local map.")
@click.option("--match", type=float, default=1.0, show_default=True,
              help="Two views are the same segment when their world centroids are this close (m).")
@click.option("--limit", type=int, default=None, help="Only the first N frames.")
def command(sequence, reader_options, out, overwrite, preset, exclude, every_map, match, limit):
    """Write the local-map segments of SEQUENCE (with poses) for ESM training."""
    from lidar_iris_eval.descriptors import get_descriptor
    from lidar_iris_eval.descriptors.esm.dataset import sequence_local_map_segments, true_pairs
    from lidar_iris_eval.io import open_sequence
    from lidar_iris_eval.ownership import check_new_files

    if exclude < 1 or every_map < 1:
        raise LirisError("--exclude/--every-map", "must be at least 1 frame")
    if not match > 0:
        raise LirisError(f"--match {match}", "must be positive")
    if out.suffix != ".npz":
        raise LirisError(f"--out {out}", "give a .npz file")
    check_new_files([out], overwrite, "--out", inputs=[sequence])  # before any work
    esm = get_descriptor("esm", preset).bind_exclusion(exclude)
    if not esm.local_map:
        raise LirisError(f"--preset {preset}", "is not a local-map preset")
    seq = open_sequence(sequence, **reader_options)

    def progress(k, n):
        if sys.stderr.isatty() and (k % 100 == 0 or k == n):
            click.echo(f"  {k}/{n} frames", err=True)

    data = sequence_local_map_segments(seq, esm, every=every_map, match=match, limit=limit,
                                       progress=progress)
    out.parent.mkdir(parents=True, exist_ok=True)
    data.save(out)
    pairs = true_pairs(data, match, min_frame_gap=esm.window)
    click.echo(json.dumps({"segments": len(data), "maps": int(len(set(data.frame.tolist()))),
                           "true_pairs": int(len(pairs)),
                           "tracks_with_pairs": int(len(set(data.object_id[pairs[:, 0]]
                                                            .tolist()))),
                           "window": esm.window, "match": match, "preset": preset}))


def main(argv=None) -> None:
    """Run :func:`command`; a bad input is one ``liris: error:`` line and exit 2."""
    run_guarded(lambda: command.main(args=argv, prog_name="esm_segments.py",
                                     standalone_mode=False))


if __name__ == "__main__":
    main()
