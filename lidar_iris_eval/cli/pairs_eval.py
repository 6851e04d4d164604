"""``liris eval SEQUENCE --pairs FILE|ssc[:N]``: PR over a list of pairs (SSC's protocol)."""

from __future__ import annotations

import click
import numpy as np

from lidar_iris_eval.cache import DescriptorCache, default_cache_dir
from lidar_iris_eval.cli.output import echo_json
from lidar_iris_eval.cli.workflow import table_format
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.evaluation.metrics import SUMMARY_KEYS
from lidar_iris_eval.runs.table import render_table
from lidar_iris_eval.runs.writer import (
    RunWriter,
    check_run_dir,
    default_run_dir,
    json_ready,
    pr_table,
    write_metrics,
)


def evaluate_pairs_cli(seq, descriptors, pairs_text, protocols, cache_dir, workers, quiet, out,
                       overwrite, as_json, executor, extra) -> None:
    """Score, write and print a pair-list run."""
    from lidar_iris_eval import __version__
    from lidar_iris_eval.config import params_dict
    from lidar_iris_eval.evaluation import metrics as m
    from lidar_iris_eval.evaluation.pairs import evaluate_pair_list
    from lidar_iris_eval.evaluation.pairs import pairs_text as as_text

    if protocols:
        raise LirisError("--protocol", "does not apply to --pairs (the list says which pairs "
                                       "count)")
    if out is None:
        out = default_run_dir(f"{seq.name}-pairs")
    check_run_dir(out, overwrite)
    cache = DescriptorCache(cache_dir if cache_dir is not None else default_cache_dir())
    pairs, results, info = evaluate_pair_list(seq, descriptors, pairs_text, cache=cache,
                                              workers=workers, progress=not quiet,
                                              executor=executor)
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
    if as_json:
        echo_json(json_ready({**header, "results": rows}))
        return
    click.echo(render_table(rows, table_format()))
    click.echo(f"pair list: {info['pair_list']} ({len(pairs)} pairs, "
               f"{int(np.count_nonzero(pairs[:, 2]))} positive); results in {out}",
               err=table_format() != "table")
