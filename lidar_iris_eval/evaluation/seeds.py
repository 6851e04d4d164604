"""Seeds and spread (issue 23): rerun the stochastic stages, report mean and range.

A method is *stochastic* when its parameters carry a ``seed`` (GOSMatch's
RANSAC, ESM's PROSAC, ESF's point-pair sampling). ``--seeds 1,2,3`` evaluates
each stochastic method once per seed (``params.seed`` replaced; ESF is
extracted again, its cache keyed by the seed) and every other method once.
The run folder holds the first seed's results (matches.csv, pr.csv, ...);
each protocol row of ``metrics.json`` gains a ``seeds`` block::

    "seeds": {"seeds": [1, 2, 3], "stochastic": true,
              "f1_max": {"values": [...], "mean": m, "min": a, "max": b}, ...}

for the metrics in :data:`SEED_METRICS` the row has (None values are left
out of mean and range; all None gives None). A deterministic method's block
says ``"stochastic": false`` and holds its single value for every seed. Each
seed's PR curve is written as ``protocol<P>/<descriptor>/pr_seed<S>.csv`` for
the band of the PR figure.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import is_dataclass, replace
from typing import Any

import numpy as np

from lidar_iris_eval.errors import LirisError, option

#: metrics summarised over seeds (when a row has them)
SEED_METRICS = ("ap", "f1_max", "r100p", "ep", "rr", "rte_m_median", "rre_deg_median",
                "refined_rr", "refined_rte_m_median", "refined_rre_deg_median")


#: seeds reach NumPy's and numba's generators, which take 32-bit seeds (``RandomState``)
MAX_SEED = 2**32 - 1


def parse_seeds(text: str | Sequence[int]) -> tuple[int, ...]:
    """``"1,2,3"`` -> ``(1, 2, 3)``: distinct non-negative integers, in the given order."""
    try:
        seeds = tuple(int(v) for v in (text.split(",") if isinstance(text, str) else text))
    except ValueError:
        raise LirisError(option("seeds", text), "expected integers, e.g. 1,2,3") from None
    if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
        raise LirisError(option("seeds", text), "give distinct non-negative integers")
    if max(seeds) > MAX_SEED:
        raise LirisError(option("seeds", text), f"seed {max(seeds)} is out of range: seeds are "
                                                f"32-bit, 0 to {MAX_SEED}")
    return seeds


def is_stochastic(descriptor) -> bool:
    params = getattr(descriptor, "params", None)
    return is_dataclass(params) and hasattr(params, "seed")


def with_seed(descriptor, seed: int):
    """A copy of ``descriptor`` whose ``params.seed`` is ``seed``."""
    return type(descriptor)(replace(descriptor.params, seed=int(seed)), preset=descriptor.preset)


def spread(values: Sequence[Any]) -> dict:
    """``values`` with their mean, min and max (None entries left out; none left: None)."""
    finite = [float(v) for v in values if v is not None and np.isfinite(v)]
    out = {"values": [None if v is None else float(v) for v in values]}
    out.update(mean=float(np.mean(finite)) if finite else None,
               min=float(np.min(finite)) if finite else None,
               max=float(np.max(finite)) if finite else None)
    return out


def _curves(result) -> dict[int, Any]:
    out = {}
    if result.protocol1 is not None:
        out[1] = result.protocol1.curve
    if result.protocol2 is not None:
        out[2] = result.protocol2.curve
    return out


def evaluate_seeds(run_once: Callable[[list], Any], descriptors: Sequence, seeds: Sequence[int]):
    """Evaluate once per seed and attach the spread to the first seed's evaluation.

    ``run_once(descriptors)`` returns an
    :class:`~lidar_iris_eval.evaluation.evaluate.Evaluation` of those
    descriptors (same sequence and settings every call). Returns the first
    seed's evaluation with ``seed_curves`` ``{(protocol, name): [(seed, curve)]}``
    and a ``seeds`` block in each row.
    """
    seeds = parse_seeds(seeds)
    first = [with_seed(d, seeds[0]) if is_stochastic(d) else d for d in descriptors]
    run = run_once(first)
    rows: dict[tuple[int, str], list[dict]] = {}
    curves: dict[tuple[int, str], list] = {}
    stochastic = {d.name for d in descriptors if is_stochastic(d)}

    def collect(evaluation, seed):
        for r in evaluation.results:
            for row in r.rows:
                rows.setdefault((row["protocol"], row["descriptor"]), []).append(row)
            for protocol, curve in _curves(r).items():
                curves.setdefault((protocol, r.descriptor.name), []).append((seed, curve))

    collect(run, seeds[0])
    again = [d for d in descriptors if is_stochastic(d)]
    for seed in seeds[1:]:
        if again:
            collect(run_once([with_seed(d, seed) for d in again]), seed)
    for key, seen in rows.items():
        name = key[1]
        per_seed = seen if name in stochastic else seen * len(seeds)
        block: dict = {"seeds": list(seeds), "stochastic": name in stochastic}
        for metric in SEED_METRICS:
            if metric in seen[0]:
                block[metric] = spread([r.get(metric) for r in per_seed])
        seen[0]["seeds"] = block
    return replace(run, seed_curves={k: v for k, v in curves.items() if k[1] in stochastic})
