"""Compiled LiDAR Iris comparison kernels (numba).

Everything that compares two LiDAR Iris descriptors runs through
:func:`pair_block`, whatever the number of pairs: one pair
(:meth:`LidarIris.distance`), one query against a database, or a block of
queries against a database. Every pair is computed by the same compiled code,
independently of its neighbours, so single-pair and batched results are bitwise
identical by construction (no BLAS, whose rounding depends on the block shape,
and no fast-math reassociation).

Per pair the work is

1. **Candidate shifts**, per match-mode branch (the candidate as given, or
   turned by half a turn: its odd harmonics change sign). ``phase``: the
   first maximum of the phase-correlation surface
   ``p(t) = sum_k Re(Z_k exp(-2 pi i k t / N))``, ``Z_k`` the normalised
   row-summed cross-power spectrum ``X_k = sum_r F1[r, k] conj(F2[r, k])`` of
   the stored low-frequency row spectra, and the window ``s - W .. s + W``
   around it. ``phase+refine``: the highest local maxima of the (unwhitened)
   band correlation, sampled every ``_COARSE_STEP`` columns and moved to the
   best column nearby. ``exhaustive``: every shift.
2. **Masked Hamming distance** of each candidate:
   ``popcount((T1s ^ T2) & ~(M1s | M2)) / popcount(~(M1s | M2))`` in exact
   integer arithmetic; the first minimum in candidate order wins, and
   ``phase+refine`` then steps to a strictly lower neighbour (+-1 column)
   while there is one. Each shift is counted once per pair.
   Features are stored per column as 64-bit words (``(words, columns)``), and
   queries are passed with their columns repeated twice, so any column roll is
   a contiguous slice; all shifts of a batch are counted in one pass over
   cache-sized column chunks, and the inner loop is a plain reduction that
   LLVM vectorises with vector popcounts where available.

Compared with the previous kernel (:mod:`.kernels_baseline`, kept as the
reference route and tested bitwise equal): the band surface is summed from
contiguous tables at the coarse columns (a vector loop over columns, each
column's sum in the same order), its maxima are ranked in one pass instead of
one scan per maximum, the fine columns around the maxima are summed together,
and the Hamming loop visits whole rows (360 columns) instead of 120-column
chunks. Integer counts do not depend on their order, and every float sum is
formed in the same order as before, so results are bitwise identical.

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
#: shift searches: the phase-correlation window, plus band peaks and descent, every shift
SEARCH_PHASE, SEARCH_REFINE, SEARCH_EXHAUSTIVE = 0, 1, 2

#: a pair is processed in tiles of this many queries x database entries, so a
#: tile's descriptors stay in cache while every pair is computed independently
_TILE_Q = 8
_TILE_M = 32
#: columns per chunk in the Hamming loop (a whole row at 360 sectors: the
#: vector loop's remainder is then paid once per word row, not three times)
_CHUNK = 360
#: the band correlation is sampled every this many columns (its peaks are
#: wide: the shortest log-Gabor wavelength is 18 columns)
_COARSE_STEP = 3


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
def _cross_spectrum(sr1, si1, sr2, si2, flip, xr, xi) -> None:
    """Row-summed cross-power spectrum ``X_k = sum_r F1[r, k] conj(F2[r, k])`` into xr, xi.

    ``flip`` turns image 2 by half a turn first (harmonic ``k`` of the rolled
    rows is multiplied by ``(-1)^k``; stored harmonics start at ``k = 1``).
    """
    rings, nk = sr1.shape
    for k in range(nk):
        xr[k] = 0.0
        xi[k] = 0.0
    # roll(img1, s) == img2 gives X_k ~ |F1|^2 exp(+2 pi i k s / N)
    for r in range(rings):
        for k in range(nk):
            a = np.float64(sr1[r, k])
            b = np.float64(si1[r, k])
            c = np.float64(sr2[r, k])
            d = np.float64(si2[r, k])
            xr[k] += a * c + b * d
            xi[k] += b * c - a * d
    if flip:
        for k in range(0, nk, 2):  # k = 1, 3, 5, ...: odd harmonics change sign
            xr[k] = -xr[k]
            xi[k] = -xi[k]


@nb.njit(cache=True, nogil=True)
def _estimate_shift(sr1, si1, sr2, si2, cos_t, sin_t, xr, xi, surf, flip=False) -> int:
    """Column shift s maximising the phase correlation of image 1 rolled by s with image 2.

    ``sr*, si*``: (rings, K) real and imaginary row spectra (bins 1..K);
    ``cos_t, sin_t``: (>= K, N) tables of cos/sin(2 pi k t / N); ``xr, xi, surf``
    are scratch buffers of length >= K, K and N. With ``flip`` image 2 is
    turned by half a turn first (the reference's reverse branch), so the
    result is the shift onto the turned image.
    """
    nk = sr1.shape[1]
    n = cos_t.shape[1]
    _cross_spectrum(sr1, si1, sr2, si2, flip, xr, xi)
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
def _band_peaks(br1, bi1, br2, bi2, cos_t, sin_t, cos_c, sin_c, flip, count, xr, xi, surf,
                out, tcol, fine) -> int:
    """The ``count`` highest local maxima of the band correlation, as columns; returns how many.

    ``br*, bi*`` are the per-row normalised, log-Gabor-weighted row spectra
    (``band_re``/``band_im``), so the surface ``sum_k Re(X_k exp(-i w k t))``
    (not whitened) approximates the summed normalised correlation of the
    filter responses whose signs the features are. It is sampled every
    ``_COARSE_STEP`` columns (``cos_c``, ``sin_c``: the tables at those
    columns, contiguous, so the sum over harmonics is a vector loop over
    columns); the refinement walks the exact distance from there.

    The maxima are ranked by value, ties to the lower column: the order of
    repeatedly taking the highest maximum not yet taken (the baseline route).
    """
    nk = br1.shape[1]
    n = cos_t.shape[1]
    m = cos_c.shape[1]
    _cross_spectrum(br1, bi1, br2, bi2, flip, xr, xi)
    for c in range(m):
        surf[c] = 0.0
    for k in range(nk):
        zr = xr[k]
        zi = xi[k]
        for c in range(m):
            surf[c] += zr * cos_c[k, c] + zi * sin_c[k, c]
    found = 0
    for c in range(m):  # one pass: keep the best `count` local maxima, sorted
        v = surf[c]
        left = surf[c - 1] if c > 0 else surf[m - 1]
        right = surf[c + 1] if c < m - 1 else surf[0]
        if not (v >= left and v > right):
            continue
        pos = found  # after every kept maximum >= v (ties: lower column first)
        while pos > 0 and surf[out[pos - 1]] < v:
            pos -= 1
        if pos >= count:
            continue
        last = min(found, count - 1)
        for f in range(last, pos, -1):
            out[f] = out[f - 1]
        out[pos] = c
        if found < count:
            found += 1
    # each peak to the best column within the coarse step: the 2 * _COARSE_STEP - 1
    # columns around every peak are summed together (independent chains, each in
    # the baseline's order); the centre's sum is surf[c] itself
    width = 2 * _COARSE_STEP - 1
    cols = found * width
    for f in range(found):
        centre = out[f] * _COARSE_STEP
        for o in range(width):
            t = centre + o - (_COARSE_STEP - 1)
            if t < 0:
                t += n
            elif t >= n:
                t -= n
            tcol[f * width + o] = t
            fine[f * width + o] = 0.0
    for k in range(nk):
        zr = xr[k]
        zi = xi[k]
        for i in range(cols):
            t = tcol[i]
            fine[i] += zr * cos_t[k, t] + zi * sin_t[k, t]
    for f in range(found):
        top = -np.inf
        for o in range(width):
            v = fine[f * width + o]
            if v > top:
                top = v
                out[f] = tcol[f * width + o]
    return found


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
def _evaluate(t1d, m1d, t2, m2, cand, count, swap, known, dist, buf, diff, masked) -> None:
    """Exact distances of the canonical shifts ``cand[:count]`` not yet in ``known``.

    ``dist[s]`` receives the masked Hamming fraction of canonical shift ``s``
    (nan when every bit is masked) and ``known[s]`` is set. The Hamming counts
    are taken with the stored query rolled by the equivalent actual shift
    (``N - s`` when the pair is swapped: rolling one side by s or the other by
    -s pairs up the same bits).
    """
    wm, n = m2.shape
    todo = 0
    for i in range(count):
        s = cand[i]
        if not known[s]:
            known[s] = True  # also de-duplicates within cand
            buf[todo] = (n - s) % n if swap else s
            todo += 1
    if todo == 0:
        return
    _window_counts(t1d, m1d, t2, m2, buf[:todo], diff, masked)
    for i in range(todo):
        s = (n - buf[i]) % n if swap else buf[i]
        valid = 2 * (wm * 64 * n - masked[i])
        dist[s] = np.nan if valid == 0 else diff[i] / valid


@nb.njit(cache=True, nogil=True)
def _pair(t1d, m1d, sr1, si1, br1, bi1, t2, m2, sr2, si2, br2, bi2, cos_t, sin_t, cos_c, sin_c,
          window, mode, search, peaks, scratch):
    """(distance, shift in columns) of one pair; shift is -1 when every bit is masked.

    Candidates are generated in the canonical pair order (see the module
    docstring): per branch (``same``: the pair as given; ``reverse``: the
    candidate turned by half a turn, the shift re-estimated and turned back),
    the phase-correlation peak and its +-window, plus with ``SEARCH_REFINE``
    the ``peaks`` highest band-correlation maxima. The first minimum in
    candidate order wins; ``SEARCH_REFINE`` then walks to a lower neighbour
    (+-1 column) while there is one. ``SEARCH_EXHAUSTIVE`` tries every shift.
    """
    xr, xi, surf, cand, buf, diff, masked, known, dist, pk, tcol, fine = scratch
    wm, n = m2.shape
    swap = _swap_needed(t1d, m1d, sr1, si1, t2, m2, sr2, si2)
    if swap:
        sr1, si1, br1, bi1, sr2, si2, br2, bi2 = sr2, si2, br2, bi2, sr1, si1, br1, bi1
    for s in range(n):
        known[s] = False
    count = 0
    if search == SEARCH_EXHAUSTIVE:
        for s in range(n):
            cand[s] = s
        count = n
    else:
        for branch in range(2):  # 0: as given, 1: candidate turned by half a turn
            if (branch == 0 and mode == MODE_REVERSE) or (branch == 1 and mode == MODE_SAME):
                continue
            back = branch * (n // 2)  # a shift onto the turned candidate, turned back
            if search == SEARCH_PHASE:
                centre = _estimate_shift(sr1, si1, sr2, si2, cos_t, sin_t, xr, xi, surf,
                                         branch == 1)
                for off in range(-window, window + 1):
                    cand[count] = (centre + back + off) % n
                    count += 1
            else:
                found = _band_peaks(br1, bi1, br2, bi2, cos_t, sin_t, cos_c, sin_c, branch == 1,
                                    peaks, xr, xi, surf, pk, tcol, fine)
                for f in range(found):
                    cand[count] = (pk[f] + back) % n
                    count += 1
    _evaluate(t1d, m1d, t2, m2, cand, count, swap, known, dist, buf, diff, masked)
    best_s = -1
    for i in range(count):  # first minimum in candidate order
        s = cand[i]
        if not np.isnan(dist[s]) and (best_s < 0 or dist[s] < dist[best_s]):
            best_s = s
    if best_s < 0:
        return np.nan, -1
    if search == SEARCH_REFINE:
        while True:  # descend the exact distance one column at a time
            cand[0] = (best_s - 1) % n
            cand[1] = (best_s + 1) % n
            _evaluate(t1d, m1d, t2, m2, cand, 2, swap, known, dist, buf, diff, masked)
            nxt = best_s
            for i in range(2):
                s = cand[i]
                if not np.isnan(dist[s]) and dist[s] < dist[nxt]:
                    nxt = s
            if nxt == best_s:
                break
            best_s = nxt
    return dist[best_s], ((n - best_s) % n if swap else best_s)


@nb.njit(cache=True, nogil=True)
def _tile(qt, qm, qsr, qsi, qbr, qbi, dt, dm, dsr, dsi, dbr, dbi, cos_t, sin_t, cos_c, sin_c,
          window, mode, search, peaks, out_d, out_s, tile, tiles_d):
    """The pairs of one tile (``_TILE_Q`` queries x ``_TILE_M`` database entries)."""
    nq = qt.shape[0]
    nd = dt.shape[0]
    nk = cos_t.shape[0]
    n = cos_t.shape[1]
    ncand = max(n, 2 * (2 * window + 1 + peaks))
    tq = tile // tiles_d
    td = tile % tiles_d
    scratch = (
        np.empty(nk),
        np.empty(nk),
        np.empty(n),
        np.empty(ncand, np.int64),
        np.empty(ncand, np.int64),
        np.empty(ncand, np.int64),
        np.empty(ncand, np.int64),
        np.empty(n, np.bool_),
        np.empty(n),
        np.empty(max(peaks, 1), np.int64),
        np.empty(max(peaks, 1) * (2 * _COARSE_STEP - 1), np.int64),
        np.empty(max(peaks, 1) * (2 * _COARSE_STEP - 1)),
    )
    for j in range(td * _TILE_M, min(nd, (td + 1) * _TILE_M)):
        for i in range(tq * _TILE_Q, min(nq, (tq + 1) * _TILE_Q)):
            d, s = _pair(
                qt[i], qm[i], qsr[i], qsi[i], qbr[i], qbi[i],
                dt[j], dm[j], dsr[j], dsi[j], dbr[j], dbi[j],
                cos_t, sin_t, cos_c, sin_c, window, mode, search, peaks, scratch,
            )  # fmt: skip
            out_d[i, j] = d
            out_s[i, j] = s


@nb.njit(cache=True, nogil=True, parallel=True)
def pair_block(qt, qm, qsr, qsi, qbr, qbi, dt, dm, dsr, dsi, dbr, dbi, cos_t, sin_t, window,
               mode, search, peaks, out_d, out_s):
    """All pairs of Q queries and M database descriptors into ``out_d``, ``out_s`` (Q, M).

    Arrays: ``qt`` (Q, 2*wm, 2N) and ``qm`` (Q, wm, 2N) uint64 hold the
    queries' words with their columns repeated twice; ``dt`` (M, 2*wm, N),
    ``dm`` (M, wm, N) the database's; ``*sr``/``*si`` (n, rings, K) and
    ``*br``/``*bi`` (n, rings, Kb) float32. Work is split into tiles over both
    axes (threads take whole tiles); each pair is computed independently, so
    results do not depend on the block shape or the thread count.
    """
    tiles_q = (qt.shape[0] + _TILE_Q - 1) // _TILE_Q
    tiles_d = (dt.shape[0] + _TILE_M - 1) // _TILE_M
    cos_c = np.ascontiguousarray(cos_t[:, ::_COARSE_STEP])
    sin_c = np.ascontiguousarray(sin_t[:, ::_COARSE_STEP])
    for tile in nb.prange(tiles_q * tiles_d):
        _tile(qt, qm, qsr, qsi, qbr, qbi, dt, dm, dsr, dsi, dbr, dbi, cos_t, sin_t, cos_c,
              sin_c, window, mode, search, peaks, out_d, out_s, tile, tiles_d)


@nb.njit(cache=True, nogil=True)
def pair_block_serial(qt, qm, qsr, qsi, qbr, qbi, dt, dm, dsr, dsi, dbr, dbi, cos_t, sin_t,
                      window, mode, search, peaks, out_d, out_s):
    """:func:`pair_block` on the calling thread: the same tiles and pair code, no parallel
    launch (which waits for every numba thread to be scheduled; for a few pairs, on a
    loaded machine, that wait cost more than the pairs)."""
    tiles_q = (qt.shape[0] + _TILE_Q - 1) // _TILE_Q
    tiles_d = (dt.shape[0] + _TILE_M - 1) // _TILE_M
    cos_c = np.ascontiguousarray(cos_t[:, ::_COARSE_STEP])
    sin_c = np.ascontiguousarray(sin_t[:, ::_COARSE_STEP])
    for tile in range(tiles_q * tiles_d):
        _tile(qt, qm, qsr, qsi, qbr, qbi, dt, dm, dsr, dsi, dbr, dbi, cos_t, sin_t, cos_c,
              sin_c, window, mode, search, peaks, out_d, out_s, tile, tiles_d)


@nb.njit(cache=True, nogil=True)
def shift_estimate(sr1, si1, sr2, si2, cos_t, sin_t) -> int:
    """The phase-correlation shift alone (no pair canonicalisation), for plots and tests."""
    nk = cos_t.shape[0]
    return _estimate_shift(
        sr1, si1, sr2, si2, cos_t, sin_t, np.empty(nk), np.empty(nk), np.empty(cos_t.shape[1])
    )
