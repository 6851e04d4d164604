"""Scan Context column-shift matching on blocks of descriptors, exact across batch shapes.

The Scan Context distance at column shift ``k`` is

    d(k) = 1 - S(k) / N(k),   S(k) = sum_c cos(q[:, c], cand[:, c - k]),

where ``N(k)`` counts the columns that are non-empty in both. Computing all
``S(k)`` pair by pair costs ``60 shifts x 1200`` multiply-adds; a full KITTI
all-pairs run (2e7 pairs) needs a cheaper route, so this module uses the
correlation theorem: with unit-length columns, ``S(k)`` is the circular
cross-correlation of the two descriptors summed over rings, i.e. the inverse
real DFT of ``sum_r F_q[r, f] * conj(F_c[r, f])``. Both the per-frequency sum
and the inverse DFT are BLAS products over whole blocks of pairs.

Exactness across batch shapes
-----------------------------
BLAS and FFT rounding depend on array shapes, yet ``distance(a, b)`` must be
bitwise equal to ``pairwise(A, B)[i, j]``. Every descriptor's unit columns are
therefore *quantised to integers* (``round(u * 2**QUANT_BITS)``): the true
correlation is then an integer far below ``2**53`` (at most ``60 * 2**32``),
the floating-point route lands within ~1e-2 of it (a worst-case bound of
about ``2e-12 * 2**32``; measured worst cases are ~6e-4 on KITTI-like and
adversarially uneven columns), and ``np.rint`` recovers it exactly whatever
the shape, threading or summation order. The sector keys (for the C++'s
pre-alignment) take the same route as unit vectors; the counts ``N(k)`` are an
exact GEMM of 0/1 validity vectors. Everything after that is element-wise, so
``distance``, ``distances`` and ``pairwise`` agree bitwise. The price is a
cosine error of order ``2**-17`` per column: ``d`` is off the exact double
value by about 2e-6 at most (``d(a, a)`` is ~2e-6, not 0), far below the 4
decimals of the authors' published numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft

#: unit columns are stored as integers in [-2**QUANT_BITS, 2**QUANT_BITS]. With
#: 16 bits a correlation is at most 60 * 2**32 ~ 2.6e11, so float64 GEMM/FFT
#: rounding (~1e-16 relative per operation) stays orders of magnitude below
#: the 0.5 that ``rint`` tolerates.
QUANT_BITS = 16
_SCALE = float(2**QUANT_BITS)
_SCALE2 = _SCALE * _SCALE

#: pairs per inner chunk, and candidates per chunk (queries per chunk =
#: CHUNK_PAIRS // CHUNK_M = 4). Besides bounding the temporaries (a few MB),
#: the sizes keep every BLAS call at most 2**18 multiply-adds
#: (``2 * 4 queries x 40 x 800``), under OpenBLAS's default threshold for
#: going multi-threaded. That is deliberate: on this 2-core machine shared
#: with other jobs, multi-threaded OpenBLAS (spinning threads) made a 4541-frame
#: all-pairs run 14x slower (142 s vs 10 s), while single-threaded calls lose
#: only ~25 % on an idle machine.
CHUNK_PAIRS = 3200
CHUNK_M = 800
#: pairs per product of the inverse DFT stack: 60 x 62 x 64 < 2**18
GEMM_COLUMNS = 64


@dataclass(frozen=True)
class Side:
    """One side (queries or candidates) of the block products, prepared once.

    Attributes
    ----------
    columns : tuple of arrays
        rFFT along sectors of the quantised unit columns, laid out for BLAS:
        queries hold ``(F, M, 2R)`` ``[Re, Im]`` and ``[Im, -Re]``; candidates
        hold one ``(F, 2R, M)`` ``[Re; Im]``. Their products give the real and
        imaginary parts of ``sum_r F_q conj(F_c)`` (``ac + bd``, ``bc - ad``).
    keys : tuple of arrays or None
        The same for the quantised unit sector key (sector-key search only).
    valid : (M, S) float64
        1.0 where the column is non-empty (non-zero norm), else 0.0.
    n_valid : (M,) int64
        Number of non-empty columns.
    """

    columns: tuple[np.ndarray, ...]
    keys: tuple[np.ndarray, ...] | None
    valid: np.ndarray
    n_valid: np.ndarray

    def __len__(self) -> int:
        return len(self.n_valid)


def quantised_unit_columns(sc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit-length columns of ``(M, R, S)`` contexts as integers, and column validity.

    The squared norm is accumulated ring by ring in a fixed order (element-wise
    adds), so a descriptor gets the same integers in any batch. Empty columns
    are all zero and stay zero.
    """
    sc = np.asarray(sc, dtype=np.float64)
    squares = sc * sc
    sq = squares[:, 0, :].copy()
    for r in range(1, sc.shape[1]):
        sq += squares[:, r, :]
    valid = sq > 0
    factor = _SCALE / np.sqrt(np.where(valid, sq, 1.0))
    unit = np.multiply(sc, factor[:, None, :], out=squares)
    np.rint(unit, out=unit)
    return unit, valid


def quantised_unit_vectors(v: np.ndarray) -> np.ndarray:
    """Rows of ``(M, S)`` scaled to unit length and quantised (zero rows stay zero).

    Scaling by a positive constant does not move the argmax of a correlation,
    so the sector-key alignment can use these integers.
    """
    v = np.asarray(v, dtype=np.float64)
    sq = v[:, 0] * v[:, 0]
    for c in range(1, v.shape[1]):
        sq += v[:, c] * v[:, c]
    factor = _SCALE / np.sqrt(np.where(sq > 0, sq, 1.0))
    return np.rint(v * factor[:, None])


def _query_layout(spec: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(M, K, F)`` complex spectra to ``(F, M, 2K)`` ``[Re, Im]`` and ``[Im, -Re]``."""
    re, im = spec.real.transpose(2, 0, 1), spec.imag.transpose(2, 0, 1)
    return np.concatenate([re, im], axis=2), np.concatenate([im, -re], axis=2)


def _candidate_layout(spec: np.ndarray) -> tuple[np.ndarray]:
    """``(M, K, F)`` complex spectra to one ``(F, 2K, M)`` ``[Re; Im]``."""
    nm, nk, nf = spec.shape
    out = np.empty((nf, 2 * nk, nm))
    out[:, :nk, :] = spec.real.transpose(2, 1, 0)
    out[:, nk:, :] = spec.imag.transpose(2, 1, 0)
    return (out,)


def prepare(sc: np.ndarray, sector_key: np.ndarray | None, role: str) -> Side:
    """Prepare ``(M, R, S)`` contexts (and ``(M, S)`` sector keys, if searched) as one side.

    ``role`` is ``"query"`` or ``"candidate"``; it only chooses the memory layout.
    """
    layout = _query_layout if role == "query" else _candidate_layout
    unit, valid = quantised_unit_columns(sc)
    keys = None
    if sector_key is not None:
        keys = layout(scipy.fft.rfft(quantised_unit_vectors(sector_key))[:, None, :])
    return Side(
        columns=layout(scipy.fft.rfft(unit, axis=-1)),
        keys=keys,
        valid=valid.astype(np.float64),
        n_valid=valid.sum(axis=1).astype(np.int64),
    )


def inverse_dft_matrix(n: int) -> np.ndarray:
    """``(n, 2F)`` real matrix mapping interleaved ``[Re X_0, Im X_0, Re X_1, ...]``
    (``F = n//2 + 1`` rFFT bins) to ``irfft(X, n)``."""
    nf = n // 2 + 1
    f = np.arange(nf)
    k = np.arange(n)
    weight = np.full(nf, 2.0)
    weight[0] = 1.0
    if n % 2 == 0:
        weight[-1] = 1.0
    angle = 2.0 * np.pi * np.outer(k, f) / n
    g = np.stack([weight * np.cos(angle), -weight * np.sin(angle)], axis=2) / n
    return g.reshape(n, 2 * nf)


def circular_correlation_exact(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``out[i, j, k] = sum_c a[i, c] * b[j, (c - k) % n]`` for integer-valued float rows.

    Used for the 0/1 validity vectors: every partial sum is a small integer,
    so the GEMM is exact in any summation order.
    """
    n = a.shape[1]
    c = np.arange(n)[:, None]
    k = np.arange(n)[None, :]
    rolled = b[:, (c - k) % n]  # (Mb, n_c, n_k)
    rolled = np.ascontiguousarray(rolled.transpose(1, 0, 2)).reshape(n, -1)
    return (a @ rolled).reshape(a.shape[0], b.shape[0], n)


def correlation(
    query: tuple[np.ndarray, ...], cand: tuple[np.ndarray, ...], qs: slice, ms: slice, g
) -> np.ndarray:
    """Exact integer circular correlations for pairs ``qs x ms``: ``(n, Qc, Mc)``.

    The product ``(F, 2 Qc, 2K) @ (F, 2K, Mc)`` holds ``Re X`` then ``Im X``
    per frequency, the interleaved order :func:`inverse_dft_matrix` expects;
    ``rint`` then removes the rounding of the float route. The inverse DFT
    runs as a stack of products over :data:`GEMM_COLUMNS` pairs each, so
    every BLAS call stays single-threaded (see :data:`CHUNK_PAIRS`).
    """
    a = np.concatenate([query[0][:, qs], query[1][:, qs]], axis=1)
    cross = np.matmul(a, cand[0][:, :, ms])  # (F, 2, Qc, Mc)
    nf, nq, nm = cross.shape[0], cross.shape[1] // 2, cross.shape[2]
    n, pairs = g.shape[0], nq * nm
    x = cross.reshape(2 * nf, pairs)
    out = np.empty((n, pairs))
    whole = pairs - pairs % GEMM_COLUMNS
    if whole:
        stack = whole // GEMM_COLUMNS
        np.matmul(
            g,
            x[:, :whole].reshape(2 * nf, stack, GEMM_COLUMNS).transpose(1, 0, 2),
            out=out[:, :whole].reshape(n, stack, GEMM_COLUMNS).transpose(1, 0, 2),
        )
    if whole < pairs:
        np.matmul(g, x[:, whole:], out=out[:, whole:])
    np.rint(out, out=out)
    return out.reshape(n, nq, nm)


def _column_counts(pq: Side, pc: Side, qs: slice, ms: slice, n: int) -> np.ndarray:
    """``N(k)`` for the pairs ``qs x ms``, shape ``(n, Qc, Mc)`` or broadcastable ``(1, Qc, Mc)``.

    A pair in which one scan has every column valid has ``N(k)`` equal to the
    other scan's count at every shift (the KITTI norm); only pairs where both
    have empty columns need the exact correlation of validity vectors.
    """
    nq_valid, nm_valid = pq.n_valid[qs], pc.n_valid[ms]
    full_q, full_m = nq_valid == n, nm_valid == n
    counts = np.where(
        full_q[:, None], nm_valid[None, :], np.where(full_m[None, :], nq_valid[:, None], -1)
    ).astype(np.float64)
    rows, cols = np.flatnonzero(~full_q), np.flatnonzero(~full_m)
    if rows.size == 0 or cols.size == 0:
        return counts[None]
    full = np.broadcast_to(counts[None], (n, *counts.shape)).copy()
    sub = circular_correlation_exact(pq.valid[qs][rows], pc.valid[ms][cols])  # (I, J, n)
    full[:, rows[:, None], cols[None, :]] = sub.transpose(2, 0, 1)
    return full


def _best_in_window(dist: np.ndarray, start: np.ndarray, radius: int):
    """Minimum of ``dist`` (``(n, Qc, Mc)``) over shifts within ``radius`` of ``start``.

    Ties go to the smallest shift index, as in the C++ (which scans the
    window's shifts in sorted order and keeps the first strict minimum).
    """
    n = dist.shape[0]
    offsets = np.arange(-radius, radius + 1)[:, None, None]
    shifts = (start[None] + offsets) % n
    values = np.take_along_axis(dist, shifts, axis=0)
    best = values.min(axis=0)
    best_shift = np.where(values == best[None], shifts, n).min(axis=0)
    return best, best_shift


def shift_distances_block(
    pq: Side,
    pc: Side,
    qs: slice,
    ms: slice,
    g: np.ndarray,
    divide_by_sectors: bool,
    search_radius: int | None,
) -> tuple[np.ndarray, np.ndarray]:
    """Best distance and its shift for pairs ``qs x ms``: two ``(Qc, Mc)`` arrays.

    ``search_radius=None`` tries every shift; otherwise only shifts within
    ``search_radius`` of the sector-key alignment. Shifts with no column valid
    in both get ``inf``; a pair with no usable shift gets ``nan`` and shift -1.
    """
    n = g.shape[0]
    sim = correlation(pq.columns, pc.columns, qs, ms, g)
    if divide_by_sectors:
        usable = (pq.n_valid[qs][:, None] > 0) & (pc.n_valid[ms][None, :] > 0)
        denom = np.where(usable, n * _SCALE2, 0.0)[None]
    else:
        denom = _column_counts(pq, pc, qs, ms, n) * _SCALE2
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = np.divide(sim, denom, out=sim)
        dist = np.subtract(1.0, dist, out=dist)
    unusable = ~(denom > 0)
    if unusable.any():
        np.copyto(dist, np.inf, where=unusable)
    if search_radius is not None and 2 * search_radius + 1 < n:
        # first maximum of the key correlation = the C++'s first minimum distance
        start = np.argmax(correlation(pq.keys, pc.keys, qs, ms, g), axis=0)
        best, best_shift = _best_in_window(dist, start, search_radius)
    else:
        best_shift = np.argmin(dist, axis=0)
        best = np.take_along_axis(dist, best_shift[None], axis=0)[0]
    ok = np.isfinite(best)
    return np.where(ok, best, np.nan), np.where(ok, best_shift, -1)


def pairwise_shift_distances(
    pq: Side,
    pc: Side,
    divide_by_sectors: bool,
    search_radius: int | None,
    chunk_pairs: int = CHUNK_PAIRS,
    chunk_m: int = CHUNK_M,
) -> tuple[np.ndarray, np.ndarray]:
    """All pairs of prepared queries and candidates: ``(Q, M)`` distances and C++ shifts.

    ``search_radius=None`` tries every shift (then no sector keys are needed).
    Works in chunks of about ``chunk_pairs`` pairs, so memory stays bounded
    whatever the sizes passed in.
    """
    nq, nm = len(pq), len(pc)
    g = inverse_dft_matrix(pq.valid.shape[1])
    dist = np.empty((nq, nm))
    shift = np.empty((nq, nm), dtype=np.int64)
    m_step = max(1, min(nm, chunk_m))
    q_step = max(1, chunk_pairs // m_step)
    for q0 in range(0, nq, q_step):
        qs = slice(q0, min(nq, q0 + q_step))
        for m0 in range(0, nm, m_step):
            ms = slice(m0, min(nm, m0 + m_step))
            dist[qs, ms], shift[qs, ms] = shift_distances_block(
                pq, pc, qs, ms, g, divide_by_sectors, search_radius
            )
    return dist, shift
