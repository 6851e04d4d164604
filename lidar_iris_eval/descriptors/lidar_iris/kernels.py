"""Compiled LiDAR Iris comparison kernels (numba).

Everything that compares two LiDAR Iris descriptors runs through
:func:`pair_block`, whatever the number of pairs: one pair
(:meth:`LidarIris.distance`), one query against a database, or a block of
queries against a database. Every pair is computed by the same compiled code,
independently of its neighbours, so single-pair and batched results are bitwise
identical by construction (no BLAS, whose rounding depends on the block shape,
and no fast-math reassociation).

Per pair the work is

1. **Shift estimate** (1-D phase correlation over columns). The stored
   low-frequency row spectra give the row-summed cross-power spectrum
   ``X_k = sum_r F1[r, k] * conj(F2[r, k])`` for ``k = 1..K``; it is normalised
   to unit magnitude and the correlation surface
   ``p(t) = sum_k Re(Z_k exp(-2 pi i k t / N))`` is evaluated at every column
   ``t``; the first maximum is the shift ``s`` such that
   ``roll(image1, s, axis=1)`` best matches ``image2``.
2. **Masked Hamming distance** over the window ``s - W .. s + W``:
   ``popcount((T1s ^ T2) & ~(M1s | M2)) / popcount(~(M1s | M2))``, the minimum
   over the window (first minimum wins), in exact integer arithmetic.
   Features are stored per column as 64-bit words (``(words, columns)``), and
   queries are passed with their columns repeated twice, so any column roll is
   a contiguous slice; all shifts of the window are counted in one pass over
   cache-sized column chunks, and the inner loop is a plain reduction that
   LLVM vectorises with vector popcounts where available.

Pair order is canonicalised (the lexicographically smaller descriptor plays
the query for the shift estimate and the window order), which makes
``d(a, b) == d(b, a)`` exact; the shift of a swapped pair is negated.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numba import types
from numba.extending import intrinsic

#: match modes, as integers for the kernel
MODE_SAME, MODE_REVERSE, MODE_BOTH = 0, 1, 2

#: a pair is processed in tiles of this many queries x database entries, so a
#: tile's descriptors stay in cache while every pair is computed independently
_TILE_Q = 8
_TILE_M = 32
#: columns per cache chunk in the Hamming loop
_CHUNK = 120


@intrinsic
def _popcount(typingctx, x):
    """Population count of a uint64 (LLVM ``ctpop``; one instruction on x86-64)."""
    if not isinstance(x, types.Integer) or x.bitwidth != 64:
        return None

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return types.int64(x), codegen


@nb.njit(cache=True, nogil=True)
def _compare(a, b) -> int:
    """Lexicographic order of two 2-D arrays over ``b``'s columns: 1, -1 or 0 (equal).

    ``a`` may be wider than ``b`` (a doubled query); only its first columns count.
    """
    rows, cols = b.shape
    for r in range(rows):
        for c in range(cols):
            if a[r, c] != b[r, c]:
                return 1 if a[r, c] > b[r, c] else -1
    return 0


@nb.njit(cache=True, nogil=True)
def _swap_needed(t1, m1, sr1, si1, t2, m2, sr2, si2) -> bool:
    """True when descriptor 1 sorts after descriptor 2 (so the pair is swapped).

    Order: features, then mask, then spectra (as raw bit patterns). Descriptors
    equal in all three compare identically in either order, so no swap is needed.
    """
    c = _compare(t1, t2)
    if c == 0:
        c = _compare(m1, m2)
    if c == 0:
        c = _compare(sr1.view(np.uint32), sr2.view(np.uint32))
    if c == 0:
        c = _compare(si1.view(np.uint32), si2.view(np.uint32))
    return c > 0


@nb.njit(cache=True, nogil=True)
def _estimate_shift(sr1, si1, sr2, si2, cos_t, sin_t, xr, xi, surf) -> int:
    """Column shift s maximising the phase correlation of image 1 rolled by s with image 2.

    ``sr*, si*``: (rings, K) real and imaginary row spectra (bins 1..K);
    ``cos_t, sin_t``: (K, N) tables of cos/sin(2 pi k t / N); ``xr, xi, surf``
    are scratch buffers of length K, K and N.
    """
    rings, nk = sr1.shape
    n = cos_t.shape[1]
    for k in range(nk):
        xr[k] = 0.0
        xi[k] = 0.0
    # X_k = sum_r F1 conj(F2); roll(img1, s) == img2 gives X_k ~ |F1|^2 exp(+2 pi i k s / N)
    for r in range(rings):
        for k in range(nk):
            a = np.float64(sr1[r, k])
            b = np.float64(si1[r, k])
            c = np.float64(sr2[r, k])
            d = np.float64(si2[r, k])
            xr[k] += a * c + b * d
            xi[k] += b * c - a * d
    for t in range(n):
        surf[t] = 0.0
    for k in range(nk):
        mag = np.sqrt(xr[k] * xr[k] + xi[k] * xi[k])
        if mag == 0.0:
            continue
        zr = xr[k] / mag
        zi = xi[k] / mag
        for t in range(n):
            # Re(Z exp(-i w k t)) = zr cos + zi sin
            surf[t] += zr * cos_t[k, t] + zi * sin_t[k, t]
    best = 0
    for t in range(1, n):
        if surf[t] > surf[best]:
            best = t
    return best


@nb.njit(cache=True, nogil=True)
def _window_counts(t1d, m1d, t2, m2, shifts, diff, masked):
    """Differing and masked bit counts of roll(T1, s) vs T2 for every s in ``shifts``.

    ``t1d``, ``m1d``: the query's words with its columns repeated twice
    (``(words, 2N)``), so ``roll(T1, s)`` is the contiguous slice starting at
    column ``N - s``; ``t2`` (2 * wm, N) holds real-part then imaginary-part
    words and ``m2`` (wm, N) the mask shared by both (padding bits set).
    Columns are visited in chunks and every shift is applied to a chunk while
    it is in L1 cache; the innermost loop is a plain reduction that LLVM
    vectorises with vector popcounts.
    """
    wm, n = m2.shape
    ns = shifts.size
    for k in range(ns):
        diff[k] = 0
        masked[k] = 0
    for w in range(wm):
        for c0 in range(0, n, _CHUNK):
            c1 = min(n, c0 + _CHUNK)
            length = c1 - c0
            cm = m2[w, c0:c1]
            cr = t2[w, c0:c1]
            ci = t2[w + wm, c0:c1]
            for k in range(ns):
                o = c0 + n - shifts[k]
                qm = m1d[w, o : o + length]
                qr = t1d[w, o : o + length]
                qi = t1d[w + wm, o : o + length]
                d = 0
                m_count = 0
                for c in range(length):
                    m = qm[c] | cm[c]
                    keep = ~m
                    m_count += _popcount(m)
                    d += _popcount((qr[c] ^ cr[c]) & keep) + _popcount((qi[c] ^ ci[c]) & keep)
                diff[k] += d
                masked[k] += m_count


@nb.njit(cache=True, nogil=True)
def _pair(t1d, m1d, sr1, si1, t2, m2, sr2, si2, cos_t, sin_t, window, mode, scratch):
    """(distance, shift in columns) of one pair; shift is -1 when every bit is masked.

    The pair is put in canonical order for the shift estimate and the order
    of the window, and the Hamming counts are taken with the query rolled by
    the equivalent shift (rolling one side by s or the other by -s pairs up
    the same bits), so the result is the canonical pair's, mirrored.
    """
    xr, xi, surf, shifts, diff, masked = scratch
    wm, n = m2.shape
    swap = _swap_needed(t1d, m1d, sr1, si1, t2, m2, sr2, si2)
    if swap:
        s_hat = _estimate_shift(sr2, si2, sr1, si1, cos_t, sin_t, xr, xi, surf)
    else:
        s_hat = _estimate_shift(sr1, si1, sr2, si2, cos_t, sin_t, xr, xi, surf)
    ns = 0
    for branch in range(2):  # 0: around the peak, 1: the 180-degree hypothesis
        if (branch == 0 and mode == MODE_REVERSE) or (branch == 1 and mode == MODE_SAME):
            continue
        centre = s_hat + branch * (n // 2)
        for off in range(-window, window + 1):
            s = (centre + off) % n
            if swap:
                s = (n - s) % n
            shifts[ns] = s
            ns += 1
    _window_counts(t1d, m1d, t2, m2, shifts[:ns], diff, masked)
    best_d = np.nan
    best_s = -1
    for k in range(ns):  # first minimum in canonical order; "reverse" must win strictly
        valid = 2 * (wm * 64 * n - masked[k])
        if valid == 0:
            continue
        d = diff[k] / valid
        if np.isnan(best_d) or d < best_d:
            best_d = d
            best_s = shifts[k]
    return best_d, best_s


@nb.njit(cache=True, nogil=True, parallel=True)
def pair_block(qt, qm, qsr, qsi, dt, dm, dsr, dsi, cos_t, sin_t, window, mode, out_d, out_s):
    """All pairs of Q queries and M database descriptors into ``out_d``, ``out_s`` (Q, M).

    Arrays: ``qt`` (Q, 2*wm, 2N) and ``qm`` (Q, wm, 2N) uint64 hold the
    queries' words with their columns repeated twice; ``dt`` (M, 2*wm, N),
    ``dm`` (M, wm, N) the database's; ``*sr``/``*si`` (n, rings, K) float32.
    Work is split into tiles over both axes (threads take whole tiles); each
    pair is computed independently, so results do not depend on the block
    shape or the thread count.
    """
    nq = qt.shape[0]
    nd = dt.shape[0]
    nk = cos_t.shape[0]
    n = cos_t.shape[1]
    tiles_q = (nq + _TILE_Q - 1) // _TILE_Q
    tiles_d = (nd + _TILE_M - 1) // _TILE_M
    nshift = 2 * (2 * window + 1)
    for tile in nb.prange(tiles_q * tiles_d):
        tq = tile // tiles_d
        td = tile % tiles_d
        scratch = (
            np.empty(nk),
            np.empty(nk),
            np.empty(n),
            np.empty(nshift, np.int64),
            np.empty(nshift, np.int64),
            np.empty(nshift, np.int64),
        )
        for j in range(td * _TILE_M, min(nd, (td + 1) * _TILE_M)):
            for i in range(tq * _TILE_Q, min(nq, (tq + 1) * _TILE_Q)):
                d, s = _pair(
                    qt[i], qm[i], qsr[i], qsi[i], dt[j], dm[j], dsr[j], dsi[j],
                    cos_t, sin_t, window, mode, scratch,
                )  # fmt: skip
                out_d[i, j] = d
                out_s[i, j] = s


@nb.njit(cache=True, nogil=True)
def shift_estimate(sr1, si1, sr2, si2, cos_t, sin_t) -> int:
    """The phase-correlation shift alone (no pair canonicalisation), for plots and tests."""
    nk = cos_t.shape[0]
    return _estimate_shift(
        sr1, si1, sr2, si2, cos_t, sin_t, np.empty(nk), np.empty(nk), np.empty(cos_t.shape[1])
    )
