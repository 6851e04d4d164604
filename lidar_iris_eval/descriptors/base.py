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
* ``inputs`` names what a method reads from a scan: ``"points"`` (default),
  ``"intensity"``, ``"labels"`` (SemanticKITTI per-point labels) or
  ``"objects"`` (an object layout's scans) or ``"local_map"`` (the pipeline
  builds each frame's local map, :mod:`lidar_iris_eval.localmaps`, and hands
  ``compute`` a ``LocalMapFrame``). The pipeline checks the sequence
  provides them before any work and calls :meth:`Descriptor.describe`, which
  hands ``compute`` the bare points (global point descriptors) or the whole
  scan (anything that reads more, or sets ``takes_scan``).
* ``compute`` may also return a *feature set*, ``dict[str, np.ndarray]``,
  whose arrays may differ in their first dimension between scans (segments,
  objects, keypoints). The pipeline keeps them as
  :class:`~lidar_iris_eval.descriptors.features.RaggedFeatures`.
* **Two-stage methods** (``two_stage = True``) have no all-pairs distance:
  :meth:`prepare` builds a database once, :meth:`retrieve` proposes candidates
  among the allowed frames, :meth:`verify` checks them geometrically and
  returns a :class:`Verification` (score, 4x4 pose, inliers). A global
  descriptor may implement :meth:`retrieve` too (Scan Context's ring-key
  search); protocol 1 then offers ``candidates=K``.

Pose convention
---------------
A relative pose ``T`` (4x4) of a match ``(query i, candidate j)`` maps points
of the candidate's LiDAR frame into the query's LiDAR frame:
``p_i = T @ p_j``; the ground truth is ``inv(P_i) @ P_j`` for LiDAR-frame
poses ``P``. For a yaw-only estimate with ``yaw_deg`` as defined above (the
candidate's *points* are the query's turned CCW by ``yaw_deg``), ``T`` is a
rotation by ``-yaw_deg`` about +z with unknown (NaN) translation; see
:func:`yaw_to_pose`.
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from lidar_iris_eval.errors import LirisError

#: every input a method may declare in ``Descriptor.inputs``
KNOWN_INPUTS = frozenset({"points", "intensity", "labels", "objects", "local_map"})
#: inputs the pipeline builds itself (``local_map``: lidar_iris_eval.localmaps, from
#: the scans and poses every sequence has), never missing from a sequence
BUILT_INPUTS = frozenset({"local_map"})


def shares_rows(descriptor: Any) -> bool:
    """True for a method whose cached rows may serve another frame selection.

    Its class says ``per_frame`` and it reads no local map (a local map mixes the
    scans of earlier frames, so a frame's row depends on which frames were kept).
    """
    return bool(getattr(descriptor, "per_frame", False)) and not reads_local_maps(descriptor)


def reads_local_maps(descriptor: Any) -> bool:
    """True for a method that declares the ``local_map`` input.

    The one test of "this method reads local maps": the extraction pipeline
    (cache key, code hash, odometry), :meth:`Descriptor.run_info` and the CLI's
    ``--odometry`` check all ask it, so they cannot disagree. An object without
    ``inputs`` (not a :class:`Descriptor`) reads none.
    """
    return "local_map" in getattr(descriptor, "inputs", ())


@dataclass(frozen=True)
class Verification:
    """Result of verifying ``k`` candidates of one query.

    Attributes
    ----------
    score : ``(k,)`` float64; smaller = more similar (as a distance);
        ``nan`` or ``inf`` = rejected.
    pose : ``(k, 4, 4)`` float64, each mapping points of the candidate's LiDAR
        frame into the query's; NaN entries where unknown (e.g. translation of
        a yaw-only estimate).
    inliers : ``(k,)`` int64 inlier count of the geometric check (0 if none).
    yaw_deg : optional ``(k,)`` yaw in the descriptor convention (module
        docstring), for global descriptors whose native output is a yaw; it
        is reported as is in ``matches.csv`` (no round trip through ``pose``).
    """

    score: np.ndarray
    pose: np.ndarray
    inliers: np.ndarray
    yaw_deg: np.ndarray | None = None

    def __post_init__(self) -> None:
        k = len(self.score)
        if np.shape(self.pose) != (k, 4, 4) or np.shape(self.inliers) != (k,):
            raise ValueError(
                f"Verification of {k} candidates needs pose (k, 4, 4) and inliers (k,), got "
                f"{np.shape(self.pose)} and {np.shape(self.inliers)}"
            )


def yaw_to_pose(yaw_deg: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` poses of yaw estimates (base-class convention), translation NaN.

    The candidate's points are the query's turned CCW by ``yaw_deg``, so the
    map candidate -> query turns them back: ``Rz(-yaw_deg)``. NaN yaw (no
    estimate: M2DP, ESF) gives an all-NaN rotation, so all nine rotation
    entries of matches.csv are empty, as docs/results-format.md says.
    """
    yaw = np.deg2rad(np.asarray(yaw_deg, dtype=np.float64))
    c, s = np.cos(-yaw), np.sin(-yaw)
    T = np.zeros((*yaw.shape, 4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 1, 0], T[..., 1, 1] = c, -s, s, c
    T[..., 2, 2] = 1.0
    T[np.isnan(yaw), :3, :3] = np.nan
    T[..., :3, 3] = np.nan
    T[..., 3, 3] = 1.0
    return T


class Descriptor(abc.ABC):
    """Base class: a named, parameterised global descriptor with a distance."""

    #: registry name, e.g. ``"lidar-iris"``
    name: ClassVar[str]
    #: frozen dataclass type holding every parameter
    params_type: ClassVar[type]
    #: True when ``distance(a, b) == distance(b, a)`` by construction, so
    #: all-pairs evaluation may compute each unordered pair once.
    symmetric: ClassVar[bool] = False
    #: what ``compute`` reads from a scan (subset of :data:`KNOWN_INPUTS`)
    inputs: ClassVar[frozenset[str]] = frozenset({"points"})
    #: inputs used when the scan has them and not required (ESM's ``ground: auto`` takes the
    #: labels where they exist): read with the scan and part of the cache key, never checked
    optional_inputs: ClassVar[frozenset[str]] = frozenset()
    #: pass the whole scan to ``compute`` even if ``inputs`` is only points
    takes_scan: ClassVar[bool] = False
    #: True for retrieval + verification methods without an all-pairs distance
    two_stage: ClassVar[bool] = False
    #: True when ``compute``'s output for a scan depends on that scan alone (no state kept
    #: across scans, no local map, a random generator restarted per scan): extraction
    #: may then take a scan's row from the cached run of another frame selection that
    #: holds the same scan (cache.py, row index). False by default, since a wrong True
    #: would serve numbers a fresh run does not give; ESM and MapClosures keep it False.
    per_frame: ClassVar[bool] = False
    #: True when ``pairwise`` runs on one thread and spends its time in calls that
    #: release the GIL (NumPy, BLAS, FFT on whole blocks): a local executor may then run
    #: several blocks of a matching pass at once on threads of this process
    #: (:meth:`~lidar_iris_eval.executor.SerialExecutor.run_blocks`). False for kernels
    #: that already use every core (numba ``prange``) and for pure-Python ones.
    threaded_blocks: ClassVar[bool] = False
    #: how figures and tables name the method (default: the registry name)
    label: ClassVar[str | None] = None
    #: its colour in every figure (default: a stable spare colour picked from its name)
    color: ClassVar[str | None] = None

    def __init__(self, params: Any = None, preset: str = "custom"):
        self.params = self.params_type() if params is None else params
        self.preset = preset

    def __repr__(self) -> str:
        return f"{type(self).__name__}(preset={self.preset!r}, params={self.params!r})"

    @abc.abstractmethod
    def compute(self, points: np.ndarray) -> np.ndarray:
        """Describe one scan: ``(N, 3)`` float32 points to a fixed-shape array.

        Methods with ``takes_scan`` or inputs beyond points receive the whole
        scan instead, and may return a feature set (``dict`` of arrays).
        """

    def distance(self, query: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        """Distance and yaw (degrees, or nan) between two descriptors.

        Every global descriptor implements it; a two-stage method has none.
        """
        raise NotImplementedError(f"{self.name} has no all-pairs distance (two-stage method)")

    def run_info(self) -> dict[str, Any]:
        """Flat keys this method adds to its rows of metrics.json (default none).

        For settings a reader needs beside the metrics, such as the local maps
        a method ran on; called after matching. A method that reads local maps
        reports what built them (odometry ``gt`` is an oracle).
        """
        if reads_local_maps(self) and hasattr(self, "local_map_settings"):
            lm = self.local_map_settings()
            return {"local_map_window": lm.window, "odometry": lm.odometry,
                    "input_filter": lm.input_filter}
        return {}

    @classmethod
    def wants_scan(cls) -> bool:
        """True when ``compute`` takes the whole scan rather than bare points."""
        return cls.takes_scan or bool(set(cls.inputs) - {"points"})

    def describe(self, scan: Any) -> Any:
        """Describe one scan as the pipeline does: the right input to :meth:`compute`.

        ``scan`` is an :class:`~lidar_iris_eval.io.scans.Scan` (or an object
        layout's scan). Global point descriptors get ``scan.points``, so their
        numbers are exactly those of ``compute(points)``.
        """
        if not self.wants_scan():
            return self.compute(scan.points)
        for name in ("intensity", "labels"):
            if name in self.inputs and getattr(scan, name, None) is None:
                raise LirisError(self.name, f"needs per-point {name}, but the scan has none")
        return self.compute(scan)

    def read_inputs(self) -> frozenset[str]:
        """Everything the pipeline reads for this method: ``inputs`` and ``optional_inputs``."""
        return frozenset(self.inputs) | frozenset(self.optional_inputs)

    def check_inputs(self, sequence: Any) -> None:
        """Raise a LirisError naming where the missing inputs would be.

        ``sequence.provides`` (a set of input names) says what its scans
        carry; sequences without it provide points only.
        """
        unknown = set(self.inputs) - KNOWN_INPUTS
        if unknown:
            raise ValueError(f"{self.name}.inputs has unknown names {sorted(unknown)}")
        provides = set(getattr(sequence, "provides", {"points", "intensity"})) | BUILT_INPUTS
        missing = sorted(set(self.inputs) - provides)
        if not missing:
            return
        where = getattr(sequence, "labels_dir", None) if missing == ["labels"] else None
        source = where if where is not None else getattr(sequence, "path", self.name)
        what = " and ".join(missing)
        detail = (f"no SemanticKITTI .label files in {where}" if where is not None
                  else f"this input has no {what}")
        raise LirisError(source, f"{self.name} needs per-point {what}; {detail}")

    # ------------------------------------------------------------ two-stage interface

    def prepare(self, features: Any) -> Any:
        """The database for :meth:`retrieve`/:meth:`verify`, built once per sequence.

        The default keeps the stacked descriptors (or ragged features) as they are.
        """
        return features

    def retrieve(
        self, db: Any, query: int, n_allowed: int, k: int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Up to ``k`` candidates among frames ``[0, n_allowed)``, best first.

        Returns ``(indices (k',) int64, retrieval distances (k',) float64)``.
        Only methods with a retrieval stage implement it.
        """
        raise NotImplementedError(f"{self.name} has no retrieval stage")

    @classmethod
    def has_retrieval(cls) -> bool:
        """True when the class implements :meth:`retrieve`."""
        return cls.retrieve is not Descriptor.retrieve

    def default_candidates(self) -> int:
        """Candidates per query when none are asked for: ``params.num_candidates`` or 10."""
        return int(getattr(self.params, "num_candidates", 10))

    def verify(self, db: Any, query: int, candidates: np.ndarray) -> Verification:
        """Score candidates of ``query`` (smaller = more similar) with a pose each.

        The default, for global descriptors, is the full distance of each
        candidate and the yaw-only pose of its yaw (:func:`yaw_to_pose`), with
        no inliers. Two-stage methods override it with a geometric check.
        """
        candidates = np.asarray(candidates, dtype=np.int64)
        if len(candidates) == 0:
            return Verification(np.empty(0), np.empty((0, 4, 4)), np.empty(0, np.int64))
        dist, yaw = self.distances(db[query], db[candidates])
        yaw = np.asarray(yaw, dtype=np.float64)
        return Verification(np.asarray(dist, dtype=np.float64), yaw_to_pose(yaw),
                            np.zeros(len(candidates), np.int64), yaw)

    def estimate_poses(self, features: Any, query: np.ndarray, match: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray] | None:
        """Relative poses of a global descriptor's protocol 1 matches, or None (default).

        A global descriptor whose authors estimate a pose for a retrieved match
        (after the exhaustive search, which stays the same) returns ``(Q, 4,
        4)`` poses (the match's LiDAR frame into the query's, NaN where none)
        and ``(Q,)`` inlier counts for the pairs ``(query[q], match[q])``
        (``match < 0``: no match, NaN pose). ``features`` are the sequence's
        stacked descriptors or feature sets.
        """
        return None

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
