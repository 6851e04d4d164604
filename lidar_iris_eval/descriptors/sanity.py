"""Checks that catch input which runs cleanly but cannot mean anything.

A sequence in millimetres, or with the sensor in the wrong frame, gives every
scan an empty (all-zero) or constant descriptor; both protocols then report
numbers near 0 and nothing looks wrong. :func:`warn_if_degenerate` says so.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.errors import warn

#: warn when more than this share of the scans has an empty or constant descriptor
DEGENERATE_SHARE = 0.5
#: float64 values converted at a time (8 MiB): the check must not cost memory of its own
CHECK_VALUES_PER_CHUNK = 1 << 20


def constant_rows(descriptors) -> np.ndarray | None:
    """``(N,)`` True where a scan's descriptor holds one value only (or no finite value).

    Works on plain arrays and on record arrays (all numeric fields must be
    constant); returns None for other containers (ragged feature sets).
    """
    if not isinstance(descriptors, np.ndarray) or descriptors.ndim == 0 or not len(descriptors):
        return None
    names = descriptors.dtype.names
    fields = [descriptors[n] for n in names] if names else [descriptors]
    numeric = [f for f in fields if np.issubdtype(f.dtype, np.number)]
    if not numeric:
        return None
    n = len(descriptors)
    constant = np.ones(n, dtype=bool)
    for field in numeric:
        per_row = int(np.prod(field.shape[1:], dtype=np.int64))
        if per_row == 0:
            continue
        # a few rows at a time: a float64 copy of the whole stack was 8x a uint8 LiDAR Iris
        # image (2.2 GiB of temporaries at 4541 frames, the peak of a plain liris eval)
        step = max(1, CHECK_VALUES_PER_CHUNK // per_row)
        for a in range(0, n, step):
            values = field[a : a + step].reshape(-1, per_row).astype(np.float64)
            finite = np.isfinite(values)
            low = np.where(finite, values, np.inf).min(axis=1)
            high = np.where(finite, values, -np.inf).max(axis=1)
            constant[a : a + step] &= ~(high > low)
    return constant


def likely_cause(points: np.ndarray | None) -> str:
    """A guess at why descriptors are empty, from one scan's points."""
    if points is None or len(points) == 0:
        return "the scans hold no points"
    xyz = np.asarray(points, dtype=np.float64)[:, :3]
    xyz = xyz[np.isfinite(xyz).all(axis=1)]
    if not len(xyz):
        return "the scans hold no finite points"
    ranges = np.hypot(xyz[:, 0], xyz[:, 1])
    median = float(np.median(ranges))
    if median > 500:
        return (f"the median horizontal range is {median:,.0f} file units: the points look like "
                "millimetres (or centimetres), not metres")
    if median < 0.5:
        return f"the median horizontal range is {median:.3g} m: points look scaled down"
    z = np.median(xyz[:, 2])
    return (f"the points look metric (median range {median:.1f} m, median height {z:.1f} m); "
            "check that they are in the sensor frame (z up, sensor at the origin) and fit "
            "the descriptor's range and height window")


def warn_if_degenerate(descriptors, name: str, sequence: str, sample=None) -> bool:
    """Warn when more than half of the descriptors are empty or constant.

    Parameters
    ----------
    descriptors : the stacked descriptors of a sequence.
    name : the descriptor's name; sequence : the sequence's name (for the message).
    sample : a callable returning the points of one scan, used to guess the
        cause; called only when the check fails.

    Returns True when it warned.
    """
    constant = constant_rows(descriptors)
    if constant is None or constant.mean() <= DEGENERATE_SHARE:
        return False
    first = int(np.argmax(constant))
    try:
        cause = likely_cause(sample(first) if sample is not None else None)
    except Exception:  # the hint must never hide the warning
        cause = "the cause could not be guessed"
    warn(sequence, f"{int(constant.sum())} of {len(constant)} scans give an empty or constant "
                   f"{name} descriptor, so its results cannot mean much; {cause}")
    return True
