"""LiDAR Iris compared the slow, obvious way: the per-pair reference loop.

NumPy on unpacked bool maps, independent of the packed-bit numba kernel. The
pair is put in canonical order (the lexicographically smaller descriptor, by
its stored words, plays the query), then per ``match_mode`` branch (the
candidate as given, or turned by half a turn: odd harmonics change sign) the
search proposes shifts: ``phase`` the +-``shift_window`` window around the
whitened phase-correlation peak of the row spectra, ``phase+refine`` the
``refine_peaks`` highest local maxima of the band correlation sampled every
3 columns and moved to the best column within +-2, ``exhaustive`` every shift.
Each proposed shift's masked Hamming fraction comes from ``np.roll`` on the
maps; the first minimum wins, and ``phase+refine`` then steps to a strictly
lower neighbour (-1 first, then +1) while there is one. :func:`prepare`
recomputes the maps from the image (``binary_features``), not from the stored
bits. The benchmark times it against the kernel, and the tests require
identical distances and shifts.
"""

from __future__ import annotations

import math

import numpy as np

#: the band correlation's sampling step (the kernel's ``_COARSE_STEP``)
COARSE_STEP = 3


def prepare(record, params):
    """``(record, (bits, mask))``: the per-frame maps a database would store once."""
    from lidar_iris_eval.descriptors.lidar_iris import binary_features

    return record, binary_features(record["image"], params)


def _sorts_after(ra, rb) -> bool:
    """True when record ``ra`` sorts after ``rb`` (T, then M, then spectra bit patterns)."""
    for name in ("T", "M", "spec_re", "spec_im"):
        x, y = np.asarray(ra[name]).ravel(), np.asarray(rb[name]).ravel()
        if x.dtype == np.float32:
            x, y = x.view(np.uint32), y.view(np.uint32)
        differ = np.nonzero(x != y)[0]
        if len(differ):
            return bool(x[differ[0]] > y[differ[0]])
    return False


def _cross(ra, rb, re: str, im: str, flip: bool) -> np.ndarray:
    f1 = ra[re].astype(np.float64) + 1j * ra[im].astype(np.float64)
    f2 = rb[re].astype(np.float64) + 1j * rb[im].astype(np.float64)
    x = (f1 * np.conj(f2)).sum(axis=0)
    if flip:
        x = x * (-1.0) ** np.arange(1, len(x) + 1)
    return x


def _surface(x: np.ndarray, columns: np.ndarray, n: int) -> np.ndarray:
    k = np.arange(1, len(x) + 1)[:, None]
    return np.real(x[:, None] * np.exp(-2j * np.pi * k * columns[None, :] / n)).sum(0)


def _centres(ra, rb, params, flip: bool) -> list[int]:
    n = params.sectors
    if params.shift_search == "phase":
        x = _cross(ra, rb, "spec_re", "spec_im", flip)
        z = np.divide(x, np.abs(x), out=np.zeros_like(x), where=np.abs(x) > 0)
        centre = int(np.argmax(_surface(z, np.arange(n), n)))
        return [centre + off for off in range(-params.shift_window, params.shift_window + 1)]
    x = _cross(ra, rb, "band_re", "band_im", flip)
    m = -(-n // COARSE_STEP)
    coarse = _surface(x, np.arange(m) * COARSE_STEP, n)
    is_peak = (coarse >= np.roll(coarse, 1)) & (coarse > np.roll(coarse, -1))
    peaks = sorted(np.nonzero(is_peak)[0], key=lambda c: (-coarse[c], c))[: params.refine_peaks]
    out = []
    for c in peaks:
        near = (c * COARSE_STEP + np.arange(-(COARSE_STEP - 1), COARSE_STEP)) % n
        out.append(int(near[np.argmax(_surface(x, near, n))]))
    return out


def reference_distance(a, b, params) -> tuple[float, int]:
    """``(distance, shift)`` of two prepared descriptors; ``(nan, -1)`` if no bit is valid."""
    n = params.sectors
    swap = _sorts_after(a[0], b[0])
    (ra, (t1, m1)), (rb, (t2, m2)) = (b, a) if swap else (a, b)
    cache: dict[int, float] = {}

    def dist(shift: int) -> float:
        shift %= n
        if shift not in cache:
            mask = np.roll(m1, shift, axis=1) | m2
            valid = (~mask).sum()
            diff = ((np.roll(t1, shift, axis=1) ^ t2) & ~mask).sum()
            cache[shift] = math.nan if valid == 0 else float(diff / valid)
        return cache[shift]

    if params.shift_search == "exhaustive":
        candidates = list(range(n))
    else:
        branches = {"same": [False], "reverse": [True], "both": [False, True]}
        candidates = []
        for flip in branches[params.match_mode]:
            back = n // 2 if flip else 0
            candidates += [(c + back) % n for c in _centres(ra, rb, params, flip)]
    best = -1
    for c in candidates:
        d = dist(c)
        if not math.isnan(d) and (best < 0 or d < dist(best)):
            best = c % n
    if best < 0:
        return math.nan, -1
    if params.shift_search == "phase+refine":
        while True:
            step = best
            for s in ((best - 1) % n, (best + 1) % n):
                if not math.isnan(dist(s)) and dist(s) < dist(step):
                    step = s
            if step == best:
                break
            best = step
    return dist(best), ((n - best) % n if swap else best)
