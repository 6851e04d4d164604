"""LiDAR Iris compared the slow, obvious way: the per-pair reference loop.

NumPy on unpacked bool maps, independent of the packed-bit numba kernel:
the phase correlation from the stored row spectra (a complex exponential
per harmonic and column) picks the centre shift, then for every shift of
the window (around the centre, or the centre + half a turn, per
``match_mode``) the query's maps are rolled with ``np.roll`` and a masked
Hamming fraction is counted. :func:`prepare` recomputes the maps from the
image (``binary_features``), not from the stored bits. The benchmark times
it against the kernel; the kernel must give identical distances.
"""

from __future__ import annotations

import math

import numpy as np


def prepare(record, params):
    """``(record, (bits, mask))``: the per-frame maps a database would store once."""
    from lidar_iris_eval.descriptors.lidar_iris import binary_features

    return record, binary_features(record["image"], params)


def reference_distance(a, b, params) -> tuple[float, int]:
    """``(distance, shift)`` of two prepared descriptors; ``(nan, -1)`` if no bit is valid."""
    (ra, (t1, m1)), (rb, (t2, m2)) = a, b
    f1 = ra["spec_re"].astype(np.float64) + 1j * ra["spec_im"].astype(np.float64)
    f2 = rb["spec_re"].astype(np.float64) + 1j * rb["spec_im"].astype(np.float64)
    cross = (f1 * np.conj(f2)).sum(axis=0)
    size = np.abs(cross)
    unit = np.divide(cross, size, out=np.zeros_like(cross), where=size > 0)
    n = params.sectors
    k = np.arange(1, len(unit) + 1)[:, None]
    surface = np.real(unit[:, None] * np.exp(-2j * np.pi * k * np.arange(n)[None, :] / n)).sum(0)
    centre = int(np.argmax(surface))
    centres = {"same": [centre], "reverse": [centre + n // 2],
               "both": [centre, centre + n // 2]}[params.match_mode]
    best, best_shift = math.nan, -1
    for c in centres:
        for shift in range(c - params.shift_window, c + params.shift_window + 1):
            mask = np.roll(m1, shift, axis=1) | m2
            valid = (~mask).sum()
            if valid == 0:
                continue
            d = ((np.roll(t1, shift, axis=1) ^ t2) & ~mask).sum() / valid
            if math.isnan(best) or d < best:
                best, best_shift = float(d), shift % n
    return best, best_shift
