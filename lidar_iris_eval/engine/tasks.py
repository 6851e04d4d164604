"""Dask tasks: extraction chunks and matching blocks that return reductions only.

The block boundaries, the per-block arithmetic and the reductions are those
of the local pass (:func:`~lidar_iris_eval.matching.blocks.affinity_matrix`
with the streaming counter of :mod:`~lidar_iris_eval.evaluation.streaming_pr`),
and merging them is exact (integer sums, minima, maxima), so a Dask run gives
bit-for-bit the metrics of a local one.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from lidar_iris_eval.evaluation.streaming_pr import (
    PositivePredictions,
    StreamingPR,
    count_block,
)


# ------------------------------------------------------------------------ extraction
def extract_chunk(seq, descriptor, a: int, b: int):
    """Descriptors of scans ``[a, b)`` (the local pool's task, on a Dask worker)."""
    from lidar_iris_eval.extract import _compute_range

    return _compute_range(seq, descriptor, a, b)


def compute_chunks(engine, seq, descriptor, todo: list[tuple[int, int]], bar) -> Iterable:
    """Yield ``((a, b), arrays)`` as the cluster finishes each chunk (any order)."""
    from distributed import as_completed

    from lidar_iris_eval.extract import _raise_errors

    client = engine.client
    [seq_f, desc_f] = client.scatter([seq, descriptor], broadcast=True, hash=False)
    futures = {client.submit(extract_chunk, seq_f, desc_f, a, b, pure=False): (a, b)
               for a, b in todo}
    try:
        for future in as_completed(futures):
            a, b = futures[future]
            arrays = _raise_errors(future.result())
            bar.update(b - a)
            yield (a, b), arrays
    finally:
        for future in futures:
            future.cancel()


# -------------------------------------------------------------------------- matching
def protocol2_block(descriptor, descriptors, template: StreamingPR, pp: PositivePredictions,
                    expected: np.ndarray, a: int, b: int, exclude: int | None) -> dict[str, Any]:
    """One block of rows ``[a, b)``: negative counts, positives, protocol 1 best matches."""
    from lidar_iris_eval.matching.blocks import _best_in_block, _pairwise

    symmetric = bool(descriptor.symmetric)
    n = len(descriptors)
    width = b if symmetric else n
    start = time.perf_counter()
    d, y = _pairwise(descriptor, descriptors[a:b], descriptors[:width])
    seconds = time.perf_counter() - start
    out: dict[str, Any] = {"a": a, "b": b, "evaluations": d.size, "seconds": seconds}
    if exclude is not None:
        first = min(exclude, n)
        if b > first:
            lo = max(a, first)
            rows = slice(lo - a, b - a)
            out["p1"] = (lo, *_best_in_block(d[rows], y[rows], np.arange(lo, b), exclude))
    acc = template.fresh()
    out["positives"], out["mismatch"] = count_block(acc, pp, expected, symmetric, a, b,
                                                    d.astype(np.float32))
    out["counts"] = acc
    return out


def stream_blocks(engine, descriptor, descriptors, template: StreamingPR,
                  pp: PositivePredictions, expected: np.ndarray, blocks: list[tuple[int, int]],
                  exclude: int | None, progress: Callable[[int], object] | None
                  ) -> dict[str, Any]:
    """Run every block as a task and merge the reductions (exactly).

    Returns the merged accumulator, the block-computed positive values, the
    mismatch flag, protocol 1's per-row results (or None), evaluations and
    the summed task compute time.
    """
    from distributed import as_completed

    client = engine.client
    n = len(descriptors)
    [desc_f, descs_f, tmpl_f, pp_f, exp_f] = client.scatter(
        [descriptor, descriptors, template, pp, expected], broadcast=True, hash=False)
    futures = [client.submit(protocol2_block, desc_f, descs_f, tmpl_f, pp_f, exp_f, a, b,
                             exclude, pure=False) for a, b in blocks]
    acc = template.fresh()
    gathered = np.empty_like(expected)
    mismatch = False
    evaluations, seconds = 0, 0.0
    p1 = None
    if exclude is not None:
        first = min(exclude, n)
        p1 = (np.empty(n - first, dtype=np.int64), np.empty(n - first), np.empty(n - first), first)
    try:
        for future in as_completed(futures):
            r = future.result()
            acc.merge(r["counts"])
            gathered[pp.in_rows(r["a"], r["b"])] = r["positives"]
            mismatch |= bool(r["mismatch"])
            evaluations += int(r["evaluations"])
            seconds += float(r["seconds"])
            if p1 is not None and "p1" in r:
                lo, match, dist, yaw = r["p1"]
                k = slice(lo - p1[3], lo - p1[3] + len(match))
                p1[0][k], p1[1][k], p1[2][k] = match, dist, yaw
            if progress is not None:
                progress(r["b"] - r["a"])
            future.release()
    finally:
        for future in futures:
            future.cancel()
    return {"acc": acc, "gathered": gathered, "mismatch": mismatch, "p1": p1,
            "evaluations": evaluations, "task_seconds": seconds}


def protocol1_block(descriptor, descriptors, a: int, b: int, exclude: int):
    """Best match of queries ``[a, b)`` over ``j <= i - exclude`` (the local pass's block)."""
    from lidar_iris_eval.matching.blocks import _best_in_block, _pairwise

    start = time.perf_counter()
    d, y = _pairwise(descriptor, descriptors[a:b], descriptors[: b - exclude])
    seconds = time.perf_counter() - start
    return a, b, d.size, seconds, _best_in_block(d, y, np.arange(a, b), exclude)


def best_matches_on_cluster(engine, descriptor, descriptors, exclude: int, pair_budget: int,
                            progress: Callable[[int], object] | None = None):
    """Protocol 1's exhaustive search with every block a task (same blocks, same results)."""
    from distributed import as_completed

    from lidar_iris_eval.matching.blocks import BestMatches, block_rows, query_blocks

    client = engine.client
    n = len(descriptors)
    first = min(exclude, n)
    queries = np.arange(first, n)
    match = np.empty(len(queries), dtype=np.int64)
    dist = np.empty(len(queries))
    yaw = np.empty(len(queries))
    [desc_f, descs_f] = client.scatter([descriptor, descriptors], broadcast=True, hash=False)
    start = time.perf_counter()
    futures = [client.submit(protocol1_block, desc_f, descs_f, a, b, exclude, pure=False)
               for a, b in query_blocks(first, n, block_rows(n, pair_budget))]
    evaluations = 0
    try:
        for future in as_completed(futures):
            a, b, size, _, (m, d, y) = future.result()
            k = slice(a - first, b - first)
            match[k], dist[k], yaw[k] = m, d, y
            evaluations += int(size)
            if progress is not None:
                progress(b - a)
            future.release()
    finally:
        for future in futures:
            future.cancel()
    seconds = time.perf_counter() - start
    return BestMatches(queries, match, dist, yaw, seconds, evaluations, "exhaustive")
