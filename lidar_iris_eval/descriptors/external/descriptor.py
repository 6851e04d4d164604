"""Bring your own descriptors: an ``.npy`` file evaluated as any global descriptor.

``liris eval SEQ --external NAME=PATH`` wraps the file in an
:class:`ExternalDescriptor`, so protocol 1 and 2, the run folder and the
figures treat it exactly as a built-in method (it is only never *computed*:
``compute`` refuses, and the stacked array comes from the file).

Two kinds of file:

* ``(N, D)`` vectors, one row per scan in frame order, compared with
  ``metric``: ``l2`` (Euclidean), ``cosine`` (``1 - a.b / (|a| |b|)``) or
  ``l1``. L2 uses the same float64 reduction as M2DP's distance, so the M2DP
  descriptors that liris computed, saved and read back give M2DP's metrics
  bit for bit.
* an ``(N, N)`` distance matrix: ``[i, j]`` = distance of query ``i`` to
  database frame ``j`` (smaller = more similar). The stacked "descriptors"
  are then frame indices and a distance is a table look-up.

A wrong ``N``, a non-numeric array or any NaN/inf is a
:class:`~lidar_iris_eval.errors.LirisError` naming the file.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.vector_common import pairwise_blocks
from lidar_iris_eval.errors import LirisError

#: vector metrics offered for ``(N, D)`` files
METRICS = ("l2", "cosine", "l1")
PRESET = "external"


@dataclass(frozen=True)
class ExternalParams:
    """Where the descriptors come from, recorded in ``config.yaml``.

    ``kind`` is ``vectors`` or ``matrix``; ``metric`` is None for a matrix;
    ``sha256`` identifies the file's content.
    """

    path: str = ""
    kind: str = "vectors"
    metric: str | None = "l2"
    sha256: str = ""


def _l2(query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    # Same operations, order and dtype as M2DP's distance: bitwise-equal results.
    diff = np.asarray(rows, dtype=np.float64) - np.asarray(query, dtype=np.float64)
    diff *= diff
    return np.sqrt(np.sum(diff, axis=-1))


def _l1(query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    diff = np.asarray(rows, dtype=np.float64) - np.asarray(query, dtype=np.float64)
    return np.sum(np.abs(diff), axis=-1)


def _cosine(query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    # Element-wise products summed along the row, so d(a, b) == d(b, a) exactly.
    q = np.asarray(query, dtype=np.float64)
    r = np.asarray(rows, dtype=np.float64)
    dot = np.sum(q * r, axis=-1)
    norms = np.sqrt(np.sum(q * q, axis=-1)) * np.sqrt(np.sum(r * r, axis=-1))
    with np.errstate(invalid="ignore", divide="ignore"):
        return 1.0 - dot / norms


_KERNELS = {"l2": _l2, "l1": _l1, "cosine": _cosine}


class ExternalDescriptor(Descriptor):
    """Descriptors read from a file; ``name`` is the user's label for the method."""

    name = "external"
    params_type = ExternalParams
    symmetric = True  # all three metrics are symmetric element by element; a matrix is checked

    def __init__(self, params: ExternalParams | None = None, preset: str = PRESET,
                 name: str = "external", array: np.ndarray | None = None):
        super().__init__(params, preset)
        self.name = name  # type: ignore[misc]  # one instance per user-named method
        self.array = array
        if self.params.kind == "matrix" and array is not None:
            self.symmetric = bool(np.array_equal(array, array.T))  # type: ignore[misc]

    def compute(self, points: np.ndarray) -> np.ndarray:
        raise LirisError(self.params.path or self.name,
                         "external descriptors are read from their file, not computed from scans")

    def stacked(self) -> np.ndarray:
        """What the matching code indexes: the vectors, or frame indices for a matrix."""
        if self.array is None:
            raise LirisError(self.name, "no descriptor array loaded")
        if self.params.kind == "matrix":
            return np.arange(len(self.array), dtype=np.int64)
        return self.array

    def distance(self, query: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        d, _ = self.pairwise(np.asarray(query)[None], np.asarray(candidate)[None])
        return float(d[0, 0]), float("nan")

    def distances(self, query: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d, y = self.pairwise(np.asarray(query)[None], database)
        return d[0], y[0]

    def pairwise(self, queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.params.kind == "matrix":
            q = np.asarray(queries, dtype=np.int64).reshape(-1)
            m = np.asarray(database, dtype=np.int64).reshape(-1)
            d = np.asarray(self.array[np.ix_(q, m)], dtype=np.float64)
            return d, np.full(d.shape, np.nan)
        return pairwise_blocks(_KERNELS[self.params.metric], queries, database)


def parse_external_spec(spec: str) -> tuple[str, Path]:
    """``"NAME=PATH"`` to ``(NAME, PATH)``."""
    name, sep, path = spec.partition("=")
    name, path = name.strip(), path.strip()
    if not sep or not name or not path:
        raise LirisError(f"--external {spec}", "expected NAME=PATH, e.g. logg3d=descs.npy")
    if any(c in name for c in "/\\:, "):
        raise LirisError(f"--external {spec}", "NAME may not contain '/', ':', ',' or spaces")
    return name, Path(path)


def load_external(name: str, path: str | Path, n_frames: int, metric: str | None = None
                  ) -> ExternalDescriptor:
    """Read and check an external descriptor file for a sequence of ``n_frames`` scans.

    Without ``metric``, an ``(N, N)`` array (``N == n_frames``) is read as a
    distance matrix and any other ``(N, D)`` as L2 vectors. Giving ``metric``
    always reads vectors (so ``D == N`` vectors are not mistaken for a matrix).
    """
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "external descriptor file not found")
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as err:
        raise LirisError(path, f"not a readable .npy file ({err})") from None
    if array.dtype.kind not in "fiu" or array.ndim != 2:
        raise LirisError(path, f"expected a numeric (N, D) array or (N, N) distance matrix, "
                               f"got {array.dtype} {array.shape}")
    if array.shape[0] != n_frames:
        raise LirisError(path, f"{array.shape[0]} rows but the sequence has {n_frames} scans "
                               f"(after frame selection); one row per scan is needed")
    finite = np.isfinite(array)
    if not finite.all():
        bad = np.argwhere(~finite)[0]
        raise LirisError(path, f"{int((~finite).sum())} NaN/inf value(s), first at row "
                               f"{int(bad[0])}, column {int(bad[1])}")
    square = array.shape == (n_frames, n_frames) and n_frames > 1
    kind = "matrix" if square and metric is None else "vectors"
    metric = "l2" if metric is None else metric
    if kind == "vectors" and metric not in METRICS:
        raise LirisError(f"--external-metric {metric}", f"choose from {', '.join(METRICS)}")
    if kind == "vectors" and metric == "cosine" and np.any(~array.any(axis=1)):
        raise LirisError(path, "an all-zero row has no cosine distance")
    digest = hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()[:16]
    params = ExternalParams(path=str(path.resolve()), kind=kind,
                            metric=metric if kind == "vectors" else None, sha256=digest)
    return ExternalDescriptor(params, PRESET, name=name, array=array)
