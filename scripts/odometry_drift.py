"""KISS-ICP's drift on a sequence, as ``liris eval --odometry kiss-icp`` runs it.

    python scripts/odometry_drift.py SEQUENCE [--length 100 --length 50]

Prints one JSON object: ATE RMSE after rigid alignment, the relative translation
error (%) over each ``--length`` (lidar_iris_eval/evaluation/drift.py), the path
length, and KISS-ICP's CPU time per scan (one thread; median, mean, 90th
percentile). Needs the optional extra ``odometry``.
"""

from __future__ import annotations

import json

import click
import numpy as np

from lidar_iris_eval.evaluation.drift import drift_report
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.localmaps.odometry import KISS_ICP_SETTINGS, estimate_odometry


@click.command()
@click.argument("sequence", type=click.Path(exists=True))
@click.option("--length", "lengths", type=float, multiple=True, default=(100.0,),
              show_default=True, help="Segment length (m) of the relative error.")
def main(sequence: str, lengths: tuple[float, ...]) -> None:
    seq = open_sequence(sequence)
    run = estimate_odometry(seq, "kiss-icp", progress=True)
    ms = run.seconds * 1e3
    report = {"sequence": str(sequence), "scans": len(seq), "kiss_icp": run.version,
              "settings": KISS_ICP_SETTINGS, "derived": run.settings,
              **drift_report(run.poses, seq.poses, tuple(lengths)),
              "ms_per_scan_median": float(np.median(ms)), "ms_per_scan_mean": float(ms.mean()),
              "ms_per_scan_p90": float(np.percentile(ms, 90))}
    click.echo(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
