"""Checks that catch input which runs cleanly but cannot mean anything.

A sequence in millimetres, or with the sensor in the wrong frame, gives every
scan an empty (all-zero) or constant descriptor; both protocols then report
numbers near 0 and nothing looks wrong. :func:`warn_if_degenerate` says so,
for built-in and external (``--external``) descriptors alike: empty or
constant rows, every scan's descriptor the same, or values so large that
their distances overflow.

Such a warning qualifies a result, so it is not only printed: inside
:func:`recording_qualifiers` it is also collected, and the run writer stores
it in ``metrics.json`` (``warnings``) for ``show``, ``compare`` and ``report``.
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator

import numpy as np

from lidar_iris_eval.errors import warn

#: warn when more than this share of the scans has an empty or constant descriptor
DEGENERATE_SHARE = 0.5
#: float64 values converted at a time (8 MiB): the check must not cost memory of its own
CHECK_VALUES_PER_CHUNK = 1 << 20
#: a value this large squares past float64's maximum (1.8e308): L2 and cosine overflow
OVERFLOW_MAGNITUDE = 1e150

_QUALIFIERS: contextvars.ContextVar[list[dict] | None] = contextvars.ContextVar(
    "liris_qualifiers", default=None)


@contextlib.contextmanager
def recording_qualifiers() -> Iterator[list[dict]]:
    """Collect the warnings that qualify a result (``{"descriptor", "sequence", "warning"}``)."""
    found: list[dict] = []
    token = _QUALIFIERS.set(found)
    try:
        yield found
    finally:
        _QUALIFIERS.reset(token)


def record_qualifier(name: str, sequence: str, message: str) -> None:
    """Warn with ``message`` and, inside :func:`recording_qualifiers`, keep it for the run."""
    warn(sequence, message)
    found = _QUALIFIERS.get()
    if found is not None:
        entry = {"descriptor": name, "sequence": sequence, "warning": message}
        if entry not in found:
            found.append(entry)


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
        problem = _overflow_or_identical(descriptors)
        if problem is not None:
            record_qualifier(name, sequence, f"{problem} {name} descriptor, so its results "
                                             f"cannot mean much")
            return True
        return False
    first = int(np.argmax(constant))
    try:
        cause = likely_cause(sample(first) if sample is not None else None)
    except Exception:  # the hint must never hide the warning
        cause = "the cause could not be guessed"
    record_qualifier(name, sequence,
                     f"{int(constant.sum())} of {len(constant)} scans give an empty or "
                     f"constant {name} descriptor, so its results cannot mean much; {cause}")
    return True


def _overflow_or_identical(descriptors) -> str | None:
    """"values overflow ..." / "all N scans give the same" for a plain numeric stack, else None."""
    if (not isinstance(descriptors, np.ndarray) or descriptors.dtype.names
            or not np.issubdtype(descriptors.dtype, np.number) or descriptors.ndim < 2
            or len(descriptors) < 2):
        return None
    n = len(descriptors)
    flat = descriptors.reshape(n, -1)
    per_row = max(1, flat.shape[1])
    step = max(1, CHECK_VALUES_PER_CHUNK // per_row)
    identical = True
    for a in range(0, n, step):
        block = flat[a : a + step]
        # float32/16 cannot hold such values (their maximum is 3.4e38): only wider floats
        if np.issubdtype(block.dtype, np.floating) and block.dtype.itemsize >= 8 and (
                np.abs(block[np.isfinite(block)]) > OVERFLOW_MAGNITUDE).any():
            return (f"values beyond {OVERFLOW_MAGNITUDE:.0e} (their squared distances overflow "
                    f"float64) in the")
        identical = identical and bool((block == flat[0]).all())
    if identical:
        return f"all {n} scans give the same"
    return None
