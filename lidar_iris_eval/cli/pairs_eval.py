"""``liris eval SEQUENCE --pairs FILE|ssc[:N]``: PR over a list of pairs (SSC's protocol)."""

from __future__ import annotations

import click
import numpy as np

from lidar_iris_eval.cli.descriptor_options import open_input
from lidar_iris_eval.cli.eval_request import EvalRequest
from lidar_iris_eval.cli.output import echo_json
from lidar_iris_eval.cli.sequence_eval import sequence_descriptors
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.metrics import SUMMARY_KEYS
from lidar_iris_eval.executor import check_scheduler, open_executor
from lidar_iris_eval.runs.table import render_table
from lidar_iris_eval.runs.writer import (
    RunWriter,
    check_run_dir,
    default_run_dir,
    json_ready,
    pr_table,
    write_metrics,
)


def run_pairs(req: EvalRequest) -> None:
    """Score, write and print a pair-list run (the mode ``pairs`` of one SEQUENCE)."""
    req.refuse_convention_band()
    if req.protocols:
        raise LirisError("--protocol", "does not apply to --pairs (the list says which pairs "
                                       "count)")
    sensor, descriptors = sequence_descriptors(req)
    seq = open_input(req.sequences[0], req.reader_options)
    for d in descriptors:
        d.check_inputs(seq)
    with open_executor(check_scheduler(req.scheduler), req.workers) as executor:
        _score_pairs(req, seq, descriptors, executor,
                     {**req.config_extra(), "sensor": sensor, "odometry": req.odometry})


def _score_pairs(req: EvalRequest, seq, descriptors, executor, extra: dict) -> None:
    """Score the pair list with every descriptor; write the run folder and print it."""
    from lidar_iris_eval import __version__
    from lidar_iris_eval.config import params_dict
    from lidar_iris_eval.evaluation import metrics as m
    from lidar_iris_eval.evaluation.pairs import evaluate_pair_list
    from lidar_iris_eval.evaluation.pairs import pairs_text as as_text

    out, overwrite, fmt = req.out, req.overwrite, req.fmt
    if out is None:
        out = default_run_dir(f"{seq.name}-pairs")
    check_run_dir(out, overwrite)
    pairs, results, info = evaluate_pair_list(seq, descriptors, req.pairs_text,
                                              cache=req.cache(), workers=req.workers,
                                              progress=not req.quiet, executor=executor)
    rows = []
    for desc, db, res in results:
        rows.append({"protocol": "pairs", "descriptor": desc.name, "preset": desc.preset,
                     **{k: res.metrics[k] for k in SUMMARY_KEYS},
                     "n_pairs": res.metrics["n_pairs"], "n_positives": res.metrics["n_positives"],
                     "n_negatives": res.metrics["n_negatives"],
                     "extract_ms_per_scan": db.extract_ms_per_scan,
                     "match_us_per_pair": res.metrics["match_us_per_pair"],
                     "pair_rule": res.metrics["pair_rule"]})
    config = {"version": __version__, "kind": "pairs",
              "sequence": {"path": str(seq.path), "name": seq.name, "n_frames": len(seq),
                           "fingerprint": seq.fingerprint()},
              "descriptors": [{"name": d.name, "preset": d.preset, "params": params_dict(d.params)}
                              for d, _, _ in results],
              "protocols": ["pairs"], "pairs": info, **extra}
    header = {"version": __version__, "sequence": config["sequence"],
              "conventions": {"kind": "pairs", **info, "exclude": None,
                              "exclude_preset": "pair list",
                              "exclusion": "none: the pair list says which pairs count",
                              "positive": "label 1 in the pair list",
                              "threshold_rule": m.THRESHOLD_RULE, "ap": m.AP_DEFINITION,
                              "ep": m.EP_DEFINITION}}
    with RunWriter(out, overwrite) as writer:
        writer.write_text("pairs/pairs.txt", as_text(pairs))
        for desc, _, res in results:
            writer.write_csv(f"pairs/{desc.name}/pr.csv", pr_table(res.curve))
            writer.write_csv(f"pairs/{desc.name}/scores.csv", {
                "i": pairs[:, 0], "j": pairs[:, 1], "label": pairs[:, 2],
                "distance": np.asarray(res.distance)})
        writer.write_yaml("config.yaml", config)
        write_metrics(writer, header, rows)
    if req.as_json:
        echo_json(json_ready({**header, "results": rows}))
        return
    click.echo(render_table(rows, fmt))
    click.echo(f"pair list: {info['pair_list']} ({len(pairs)} pairs, "
               f"{int(np.count_nonzero(pairs[:, 2]))} positive); results in {out}",
               err=fmt != "table")
