"""One Scan Context pair, compared directly (numba): the online, one-query use.

:mod:`.kernels` is built for blocks of thousands of pairs: an FFT of every
column, BLAS products per frequency, an inverse DFT. For one pair that
machinery costs about 0.3 ms of set-up. This module computes the same
numbers for one pair in a few microseconds:

* the columns (and sector keys) are quantised exactly as
  :func:`.kernels.quantised_unit_columns` / :func:`.kernels.quantised_unit_vectors`
  do (same float64 operations in the same order);
* the correlation of two quantised columns at a shift is a sum of integer
  products, exact in float64 in any order (below ``60 * 2**32 < 2**53``), so
  it is summed with SIMD reassociation allowed (:func:`_dot`). The FFT route
  rounds its result to that same integer (``rint``), so both give the same
  value; only the shifts the search needs are evaluated (the 7 of the
  sector-key window, or all of them);
* the division, the window search and its tie-breaking (smallest shift
  index) are the element-wise steps of :func:`.kernels.shift_distances_block`.

The result is bitwise equal to :meth:`ScanContext.pairwise` (tested on
simulated and real scans, both searches and both divisors).
"""

from __future__ import annotations

import numba
import numpy as np

from lidar_iris_eval.descriptors.scan_context.kernels import _SCALE, _SCALE2


@numba.njit(cache=True, nogil=True, inline="always")
def _rint(x):  # pragma: no cover - compiled
    """``np.rint`` (round half to even) for ``|x| < 2**51``, without a libm call.

    Adding and subtracting ``2**52`` rounds to an integer in the current
    (nearest-even) rounding mode, symmetric in sign; no fastmath here, so the
    compiler keeps it.
    """
    big = 4503599627370496.0
    return np.copysign((abs(x) + big) - big, x)


@numba.njit(cache=True, nogil=True)
def _unit_columns(sc):  # pragma: no cover - compiled
    """Quantised unit columns, transposed to ``(S, R)`` so a column is contiguous."""
    rings, n = sc.shape
    sq = np.empty(n)
    for c in range(n):
        v = np.float64(sc[0, c])
        sq[c] = v * v
    for r in range(1, rings):  # ring by ring, as the batched route adds them
        for c in range(n):
            v = np.float64(sc[r, c])
            sq[c] += v * v
    unit = np.empty((n, rings))
    valid = np.empty(n, dtype=np.bool_)
    for c in range(n):
        valid[c] = sq[c] > 0
        factor = _SCALE / np.sqrt(sq[c] if sq[c] > 0 else 1.0)
        for r in range(rings):
            unit[c, r] = _rint(np.float64(sc[r, c]) * factor)
    return unit, valid


@numba.njit(cache=True, nogil=True)
def _unit_vector(v):  # pragma: no cover - compiled
    n = v.shape[0]
    sq = v[0] * v[0]
    for c in range(1, n):
        sq += v[c] * v[c]
    factor = _SCALE / np.sqrt(sq if sq > 0 else 1.0)
    out = np.empty(n)
    for c in range(n):
        out[c] = _rint(v[c] * factor)
    return out


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _dot(a, b):  # pragma: no cover - compiled
    """Dot product of integer-valued float64 vectors.

    Every product and partial sum is an integer below 2**53, hence exact in
    any order: reassociation (SIMD) cannot change the result.
    """
    s = 0.0
    for i in range(a.shape[0]):
        s += a[i] * b[i]
    return s


@numba.njit(cache=True, nogil=True)
def _shift_distance(uq, vq, uc, vc, k, divide_by_sectors):  # pragma: no cover - compiled
    """Distance at shift ``k``: query column c against candidate column (c - k) mod n."""
    n = uq.shape[0]
    sim = 0.0
    both = 0
    for c in range(n):
        j = c - k
        if j < 0:
            j += n
        if vq[c] and vc[j]:
            both += 1
        sim += _dot(uq[c], uc[j])
    if divide_by_sectors:
        nq = 0
        nc = 0
        for c in range(n):
            nq += vq[c]
            nc += vc[c]
        denom = n * _SCALE2 if (nq > 0 and nc > 0) else 0.0
    else:
        denom = both * _SCALE2
    if not denom > 0:
        return np.inf
    return 1.0 - sim / denom


@numba.njit(cache=True, nogil=True)
def pair_distance(sc_q, sc_c, key_q, key_c, divide_by_sectors, radius):  # pragma: no cover
    """``(distance, C++ shift)`` of one pair; ``radius < 0`` tries every shift.

    A pair with no usable shift gives ``(nan, -1)``.
    """
    uq, vq = _unit_columns(sc_q)
    uc, vc = _unit_columns(sc_c)
    n = uq.shape[0]
    best = np.inf
    best_shift = -1
    if radius >= 0 and 2 * radius + 1 < n:
        kq = _unit_vector(key_q)
        kc = _unit_vector(key_c)
        start = 0
        top = -np.inf
        for k in range(n):
            s = _dot(kq[k:], kc[: n - k]) + _dot(kq[:k], kc[n - k :])  # c - k wraps below c = k
            if s > top:  # first maximum, as np.argmax
                top = s
                start = k
        for o in range(-radius, radius + 1):
            k = (start + o + n) % n
            d = _shift_distance(uq, vq, uc, vc, k, divide_by_sectors)
            if d < best or (d == best and best_shift >= 0 and k < best_shift):
                best = d
                best_shift = k
            elif best_shift < 0 and d == best:
                best_shift = k
    else:
        for k in range(n):
            d = _shift_distance(uq, vq, uc, vc, k, divide_by_sectors)
            if d < best or best_shift < 0:  # first minimum, as np.argmin
                best = d
                best_shift = k
    if not np.isfinite(best):
        return np.nan, -1
    return best, best_shift


def distance_and_shift(
    sc_q: np.ndarray,
    sc_c: np.ndarray,
    key_q: np.ndarray,
    key_c: np.ndarray,
    divide_by_sectors: bool,
    search_radius: int | None,
) -> tuple[float, int]:
    """Python entry of :func:`pair_distance`; ``search_radius=None`` tries every shift."""
    radius = -1 if search_radius is None else int(search_radius)
    return pair_distance(sc_q, sc_c, key_q, key_c, divide_by_sectors, radius)
