"""``liris eval``: protocol 1 and/or 2 for one or more descriptors, written to a run folder."""

from __future__ import annotations

import platform
import sys
import time
from datetime import datetime
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from lidar_iris_eval import __version__
from lidar_iris_eval.cli.extract_cmd import (
    build_descriptors,
    descriptor_options,
    open_input,
    run_extraction,
)
from lidar_iris_eval.cli.options import ground_truth_options, parse_exclude
from lidar_iris_eval.cli.output import echo_json, echo_table
from lidar_iris_eval.config import params_dict
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation import metrics as m
from lidar_iris_eval.evaluation.protocol1 import REVERSE_DEGREES, protocol1
from lidar_iris_eval.evaluation.protocol2 import protocol2, protocols_1_and_2
from lidar_iris_eval.evaluation.report import (
    SUMMARY_KEYS,
    RunWriter,
    check_run_dir,
    json_ready,
    write_metrics,
    write_protocol1,
    write_protocol2,
    write_timing,
)
from lidar_iris_eval.matching.blocks import DEFAULT_PAIR_BUDGET

TABLE_COLUMNS = ("protocol", "descriptor", "preset", "ap", "f1_max", "r100p", "ep", "n",
                 "positives", "extract_ms_per_scan", "match_time")


@click.command("eval")
@click.argument("sequence", type=click.Path(path_type=Path))
@click.option("--protocol", "protocols", type=click.Choice(["1", "2"]), multiple=True,
              required=True, help="1 (best match per query) or 2 (all pairs); may be repeated.")
@descriptor_options
@ground_truth_options
@click.option("--recall-denominator", type=click.Choice(["revisits", "accepted"]),
              default="revisits", show_default=True,
              help="Protocol 1 recall: TP / revisit queries, or Scan Context's accepted-only FN.")
@click.option("--candidates", type=int, default=None,
              help="Protocol 1 only: use the descriptor's own retrieval with K candidates.")
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Run folder [default: results/<sequence>-<timestamp>].")
@click.option("--overwrite", is_flag=True, help="Replace an existing run folder.")
@click.option("--block-pairs", type=int, default=DEFAULT_PAIR_BUDGET, show_default=True,
              help="Distances computed per block (bounds memory).")
@click.option("--json", "as_json", is_flag=True, help="Print metrics.json instead of a table.")
def command(sequence, protocols, descriptor_text, preset, params, sensor, cache_dir, workers,
            quiet, radius, exclude, distance, pose_frame, recall_denominator, candidates, out,
            overwrite, block_pairs, as_json, reader_options):
    """Evaluate descriptors on SEQUENCE with protocol 1 and/or 2.

    Descriptors are extracted first when the cache lacks them. Results go to a
    run folder (docs/results-format.md) that `liris plot` reads.
    """
    protocols = sorted({int(p) for p in protocols})
    exclude_frames, exclude_name = parse_exclude(exclude)
    if radius <= 0:
        raise LirisError(f"--radius {radius}", "radius must be positive")
    if workers < 1:
        raise LirisError(f"--workers {workers}", "must be at least 1")
    if block_pairs < 1:
        raise LirisError(f"--block-pairs {block_pairs}", "must be at least 1")
    if candidates is not None and 1 not in protocols:
        raise LirisError(f"--candidates {candidates}", "only applies to --protocol 1")
    if candidates is not None and candidates < 1:
        raise LirisError(f"--candidates {candidates}", "must be at least 1")
    descriptors = build_descriptors(descriptor_text, preset, sensor, params)
    if candidates is not None:
        for d in descriptors:
            if not callable(getattr(d, "candidates", None)):
                raise LirisError(f"--candidates {candidates}",
                                 f"{d.name} has no retrieval stage; run it without --candidates")
    seq = open_input(sequence, reader_options)
    if out is None:
        out = Path("results") / f"{seq.name}-{datetime.now():%Y%m%d-%H%M%S}"
    check_run_dir(out, overwrite)
    pose_frame = seq.resolve_pose_frame(pose_frame)
    poses = seq.camera_poses if pose_frame == "camera" else seq.poses
    positions = seq.positions(pose_frame)
    forward = seq.poses[:, :3, 0]  # LiDAR x axis: the driving direction

    started = time.perf_counter()
    dbs = run_extraction(seq, descriptors, cache_dir, workers, quiet)
    settings = dict(exclude=exclude_frames, radius=radius, distance=distance, frame=pose_frame,
                    pair_budget=block_pairs)
    with RunWriter(out, overwrite) as run:
        rows = []
        for desc, db in zip(descriptors, dbs, strict=True):
            rows_to_match = len(db) if 2 in protocols else max(0, len(db) - exclude_frames)
            with tqdm(total=rows_to_match, desc=f"{desc.name} matching", unit="query",
                      file=sys.stderr, disable=quiet, leave=False) as bar:
                rows += _evaluate_one(run, desc, db, positions, forward, protocols, candidates,
                                      recall_denominator, {**settings, "progress": bar.update})
            write_timing(run, desc.name, db.extract_s, db.read_s)
        config = _config(seq, descriptors, protocols, radius, exclude_frames, exclude_name,
                         recall_denominator, distance, pose_frame, candidates, block_pairs,
                         sensor, reader_options)
        header = _header(seq, config, time.perf_counter() - started)
        run.write_yaml("config.yaml", config)
        write_metrics(run, header, rows)
        run.write_npy("poses.npy", poses.astype(np.float64))
        run.write_npy("positions.npy", positions.astype(np.float64))
    if as_json:
        echo_json(json_ready({**header, "results": rows}))
        return
    echo_table([_table_row(r) for r in rows], TABLE_COLUMNS)
    click.echo(
        f"conventions: radius {radius:g} m, exclude E={exclude_frames} ({exclude_name}), "
        f"{distance} distance, {pose_frame}-frame poses, protocol 1 recall denominator "
        f"'{recall_denominator}'; results in {out}"
    )


def _evaluate_one(run, desc, db, positions, forward, protocols, candidates, denominator,
                  settings) -> list[dict]:
    """Run the requested protocols for one descriptor, write its files, return metric rows."""
    p1 = p2 = None
    both = protocols == [1, 2] and candidates is None
    if both:
        p1, p2 = protocols_1_and_2(desc, db.descriptors, positions, recall_denominator=denominator,
                                   forward=forward, **settings)
    else:
        if 1 in protocols:
            p1 = protocol1(desc, db.descriptors, positions, recall_denominator=denominator,
                           candidates=candidates, forward=forward, **settings)
        if 2 in protocols:
            kwargs = {k: v for k, v in settings.items() if k != "exclude"}
            if p1 is not None:  # the bar counted protocol 1 already; don't overrun it
                kwargs["progress"] = None
            p2 = protocol2(desc, db.descriptors, positions, **kwargs)
    base = {"descriptor": desc.name, "preset": desc.preset}
    rows = []
    if p1 is not None:
        write_protocol1(run, desc.name, p1)
        matches = p1.matches
        n_queries = max(1, p1.metrics["n_queries"])
        rows.append({
            "protocol": 1, **base, **{k: p1.metrics[k] for k in SUMMARY_KEYS},
            "n_queries": p1.metrics["n_queries"],
            "n_positives": p1.metrics["n_positives"],
            "n_revisits": p1.metrics["n_revisits"],
            "extract_ms_per_scan": db.extract_ms_per_scan,
            "match_ms_per_query": matches.seconds / n_queries * 1e3,
            "recall_denominator": denominator,
            "match_source": matches.source,
            **{k: v for k, v in p1.metrics.items()
               if k not in SUMMARY_KEYS and k not in ("n_queries", "n_positives", "n_revisits")},
        })
    if p2 is not None:
        write_protocol2(run, desc.name, p2)
        aff = p2.affinity
        rows.append({
            "protocol": 2, **base, **{k: p2.metrics[k] for k in SUMMARY_KEYS},
            "n_pairs": p2.metrics["n_pairs"],
            "n_positives": p2.metrics["n_positives"],
            "n_negatives": p2.metrics["n_negatives"],
            "extract_ms_per_scan": db.extract_ms_per_scan,
            "match_us_per_pair": aff.seconds / max(1, aff.n_evaluations) * 1e6,
            "n_distance_evaluations": aff.n_evaluations,
            "symmetric": aff.symmetric,
            "p_at_lowest_recall": p2.metrics["p_at_lowest_recall"],
        })
    return rows


def _config(seq, descriptors, protocols, radius, exclude, exclude_name, denominator, distance,
            pose_frame, candidates, block_pairs, sensor, reader_options) -> dict:
    """Everything needed to reproduce the run (config.yaml)."""
    return {
        "version": __version__,
        "sequence": {"path": str(Path(seq.path).resolve()), "name": seq.name,
                     "n_frames": len(seq), "fingerprint": seq.fingerprint(),
                     "reader_options": {k: str(v) for k, v in reader_options.items()}},
        "sensor": sensor,
        "descriptors": [{"name": d.name, "preset": d.preset, "params": params_dict(d.params)}
                        for d in descriptors],
        "protocols": protocols,
        "radius": float(radius),
        "exclude": {"value": int(exclude), "preset": exclude_name},
        "recall_denominator": denominator,
        "distance": distance,
        "pose_frame": pose_frame,
        "candidates": candidates,
        "block_pairs": int(block_pairs),
    }


def _header(seq, config: dict, wall_s: float) -> dict:
    return {
        "version": __version__,
        "created": datetime.now().isoformat(timespec="seconds"),
        "wall_s": wall_s,
        "host": {"python": sys.version.split()[0], "platform": platform.platform()},
        "sequence": config["sequence"],
        "conventions": {
            "radius": config["radius"],
            "exclude": config["exclude"]["value"],
            "exclude_preset": config["exclude"]["preset"],
            "distance": config["distance"],
            "pose_frame": config["pose_frame"],
            "recall_denominator": config["recall_denominator"],
            "candidates": config["candidates"],
            "positive": f"ground-truth distance < {config['radius']:g} m",
            "threshold_rule": m.THRESHOLD_RULE,
            "ap": m.AP_DEFINITION,
            "ep": m.EP_DEFINITION,
            "protocol2_counts": "ordered pairs (i, j), i != j",
            "reverse_revisit": f"nearest earlier positive's heading differs by > "
                               f"{REVERSE_DEGREES:g} deg (LiDAR x axis)",
            "extract_time": "mean descriptor.compute time per scan, from the run that "
                            "filled the cache",
        },
    }


def _table_row(row: dict) -> dict:
    p1 = row["protocol"] == 1
    match_time = (f"{row['match_ms_per_query']:.3f} ms/query" if p1
                  else f"{row['match_us_per_pair']:.3f} us/pair")
    return {
        **{k: row[k] for k in ("protocol", "descriptor", "preset", *SUMMARY_KEYS[:2])},
        "r100p": row["r100p"],
        "ep": row["ep"],
        "n": row["n_queries"] if p1 else row["n_pairs"],
        "positives": row["n_positives"],
        "extract_ms_per_scan": row["extract_ms_per_scan"],
        "match_time": match_time,
    }
