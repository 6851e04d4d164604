"""The interface every place-recognition descriptor implements.

All stacking, caching and matching code works on any descriptor through this
interface, so a new method touches only its own module.

Conventions
-----------
* ``compute(points)`` takes an ``(N, 3)`` float32 array in the sensor frame
  (x forward, y left, z up) and returns a fixed-shape, fixed-dtype array. A
  descriptor made of several parts returns a NumPy *structured* scalar array
  (``shape == ()``), so that ``np.stack`` of many scans gives an ``(M,)``
  record array and ``db["part"]`` an ``(M, ...)`` block.
* ``distance(query, candidate) -> (dist, yaw_deg)``. Smaller is more similar.
  ``yaw_deg`` is the angle in ``[0, 360)`` by which the candidate scan is
  rotated counter-clockwise about +z relative to the query (if the candidate
  is the query turned CCW by 30 degrees, yaw is 30). ``nan`` when the
  descriptor does not estimate yaw.
* ``distances(query, database)`` and ``pairwise(queries, database)`` are the
  batched forms. They must return exactly the numbers of ``distance``.
"""

from __future__ import annotations

import abc
from typing import Any, ClassVar

import numpy as np


class Descriptor(abc.ABC):
    """Base class: a named, parameterised global descriptor with a distance."""

    #: registry name, e.g. ``"lidar-iris"``
    name: ClassVar[str]
    #: frozen dataclass type holding every parameter
    params_type: ClassVar[type]
    #: True when ``distance(a, b) == distance(b, a)`` by construction, so
    #: all-pairs evaluation may compute each unordered pair once.
    symmetric: ClassVar[bool] = False

    def __init__(self, params: Any = None, preset: str = "custom"):
        self.params = self.params_type() if params is None else params
        self.preset = preset

    def __repr__(self) -> str:
        return f"{type(self).__name__}(preset={self.preset!r}, params={self.params!r})"

    @abc.abstractmethod
    def compute(self, points: np.ndarray) -> np.ndarray:
        """Describe one scan: ``(N, 3)`` float32 points to a fixed-shape array."""

    @abc.abstractmethod
    def distance(self, query: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        """Distance and yaw (degrees, or nan) between two descriptors."""

    def distances(self, query: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One query against a stacked database: ``(M,)`` distances and yaws.

        The default loops over :meth:`distance`; descriptors override it with a
        vectorised kernel that returns identical numbers.
        """
        out = [self.distance(query, database[j]) for j in range(len(database))]
        if not out:
            return np.empty(0), np.empty(0)
        dists, yaws = zip(*out, strict=True)
        return np.asarray(dists, dtype=np.float64), np.asarray(yaws, dtype=np.float64)

    def pairwise(self, queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """All pairs of a block of queries and a database: ``(Q, M)`` arrays.

        The default stacks :meth:`distances`; override for block kernels.
        Callers bound memory by passing blocks of queries.
        """
        rows = [self.distances(queries[i], database) for i in range(len(queries))]
        if not rows:
            return np.empty((0, len(database))), np.empty((0, len(database)))
        return np.stack([r[0] for r in rows]), np.stack([r[1] for r in rows])

    def describe_many(self, scans) -> np.ndarray:
        """Compute and stack descriptors of an iterable of point arrays."""
        return np.stack([self.compute(points) for points in scans])
