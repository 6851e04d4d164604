"""Scan Context compared the slow, obvious way: the per-pair reference loop.

Written from the authors' description, independently of :mod:`.kernels` and
:mod:`.pair`: for each tried shift the candidate is rolled with ``np.roll``
and ``1 - cos`` is averaged over the columns non-empty in both (or summed and
divided by the number of sectors for ``divide_by: sectors``), in float64.
``sector-key`` tries ``+-search_radius`` around the first shift minimising
``||v_q - roll(v_c, s)||`` of the sector keys (column means), as the C++;
``exhaustive`` tries every shift. The benchmark times it against the
batched kernel and the tests check the kernel against it (they agree to
about 2e-6, the quantisation of :mod:`.kernels`).
"""

from __future__ import annotations

import math

import numpy as np


def per_shift_distances(q: np.ndarray, c: np.ndarray, divide_by: str = "valid") -> np.ndarray:
    """``d`` at every C++ shift ``k`` (``q`` against ``roll(c, k)``); ``inf`` if unusable."""
    q = np.asarray(q, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    n = q.shape[1]
    norm_q = np.linalg.norm(q, axis=0)
    out = np.full(n, math.inf)
    for k in range(n):
        cs = np.roll(c, k, axis=1)
        norm_c = np.linalg.norm(cs, axis=0)
        valid = (norm_q > 0) & (norm_c > 0)
        if valid.any():
            cos = (q * cs).sum(axis=0)[valid] / (norm_q * norm_c)[valid]
            out[k] = 1.0 - cos.sum() / (valid.sum() if divide_by == "valid" else n)
    return out


def sector_key_start(q: np.ndarray, c: np.ndarray) -> int:
    """The C++ alignment: the first shift minimising ``||v_q - roll(v_c, s)||``."""
    vq = np.asarray(q, dtype=np.float64).mean(axis=0)
    vc = np.asarray(c, dtype=np.float64).mean(axis=0)
    return int(np.argmin([np.linalg.norm(vq - np.roll(vc, s)) for s in range(len(vq))]))


def tried_shifts(q: np.ndarray, c: np.ndarray, search: str, radius: int) -> list[int]:
    """The shifts the search evaluates, sorted."""
    n = np.asarray(q).shape[1]
    if search == "exhaustive" or 2 * radius + 1 >= n:
        return list(range(n))
    start = sector_key_start(q, c)
    return sorted({(start + j) % n for j in range(-radius, radius + 1)})


def prepare(record, params):
    """Per-frame preparation a database would store once: here the float64 context."""
    return np.asarray(record["sc"], dtype=np.float64)


def reference_distance(q, c, params) -> tuple[float, int]:
    """``(distance, C++ shift)`` of two prepared contexts; ``(nan, -1)`` with no usable shift.

    Ties go to the smallest shift, as the C++ (first strict minimum in sorted order).
    """
    per_shift = per_shift_distances(q, c, params.divide_by)
    shifts = tried_shifts(q, c, params.search, params.search_radius)
    best = min(shifts, key=lambda k: (per_shift[k], k))
    if not math.isfinite(per_shift[best]):
        return math.nan, -1
    return float(per_shift[best]), int(best)
