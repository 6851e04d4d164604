"""Refining a loop's relative pose by registering the two scans (issue 23).

A loop ``(query i, match j)`` carries a pose ``T`` mapping points of scan
``j``'s LiDAR frame into scan ``i``'s (``descriptors/base.py``). Registration
aligns scan ``j`` (source) to scan ``i`` (target) starting from an initial
guess and returns the refined ``T`` with its *fitness*:

* the initial guess is the method's own estimate; a yaw-only estimate (LiDAR
  Iris, Scan Context: rotation known, translation NaN) starts from that
  rotation and zero translation; no estimate at all (M2DP, ESF) starts from
  the identity;
* ``gicp`` (generalized ICP) or ``icp`` (point-to-point) from the
  ``small_gicp`` library (optional extra ``registration``), both scans voxel
  downsampled to ``voxel_m``;
* fitness is measured the same way for both methods, independent of the
  library's internal cost: each downsampled source point, moved by the refined
  pose, is an *inlier* when its nearest downsampled target point lies within
  ``inlier_m``; ``inlier_ratio`` = inliers / source points and ``rmse_m`` =
  root mean square of the inlier distances (NaN with no inlier);
* ``seconds`` is the wall time of the alignment itself (downsampling, which
  is done once per scan and cached, is excluded; it is reported apart).

A scan with fewer than :data:`MIN_POINTS` points after downsampling gives a
failed registration (pose NaN, fitness NaN), never a made-up one.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lidar_iris_eval.errors import LirisError, option

#: registration methods (``--refine``)
METHODS = ("gicp", "icp")
#: fewest downsampled points a scan needs to be registered
MIN_POINTS = 20
EXTRA_HINT = "needs the optional extra: pip install 'lidar_iris_eval[registration]' (small_gicp)"


@dataclass(frozen=True)
class RegistrationSettings:
    """How scans are registered (recorded in metrics.json).

    Parameters
    ----------
    method : ``gicp`` or ``icp`` (point-to-point).
    voxel_m : voxel size of the downsampling, metres.
    max_correspondence_m : largest point distance paired during the alignment.
    max_iterations : iteration limit of the alignment.
    inlier_m : distance below which a point counts as an inlier in the fitness.
    neighbours : points per covariance estimate (GICP).
    threads : threads of the alignment.
    """

    method: str = "gicp"
    voxel_m: float = 0.25
    max_correspondence_m: float = 1.0
    max_iterations: int = 50
    inlier_m: float = 0.5
    neighbours: int = 20
    threads: int = 1

    def check(self) -> RegistrationSettings:
        if self.method not in METHODS:
            raise LirisError(option("refine", self.method),
                             f"unknown registration; choose from {', '.join(METHODS)}")
        for name in ("voxel_m", "max_correspondence_m", "inlier_m"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise LirisError(option("refine", self.method), f"{name} must be > 0, got {value}")
        if self.max_iterations < 1 or self.threads < 1 or self.neighbours < 3:
            raise LirisError(option("refine", self.method),
                             "max_iterations and threads must be >= 1, neighbours >= 3")
        return self

    def describe(self) -> dict:
        """The settings and the fitness rule, for metrics.json."""
        return {
            "method": self.method, "library": f"small_gicp {_library_version()}",
            "voxel_m": self.voxel_m, "max_correspondence_m": self.max_correspondence_m,
            "max_iterations": self.max_iterations, "inlier_m": self.inlier_m,
            "neighbours": self.neighbours,
            "initial_guess": "the method's pose; yaw-only: that rotation, zero translation; "
                             "none: identity",
            "fitness": f"inlier_ratio = share of downsampled source points within "
                       f"{self.inlier_m:g} m of the target after alignment; rmse_m over "
                       "those inliers",
        }


def _library():
    try:
        import small_gicp
    except ImportError:
        raise LirisError(option("refine", "gicp"), EXTRA_HINT) from None
    return small_gicp


def _library_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("small_gicp")
    except PackageNotFoundError:
        return "missing"


def check_available() -> None:
    """Raise the one-line error naming the extra when ``small_gicp`` is missing."""
    _library()


@dataclass(frozen=True)
class Registration:
    """One refined pose: ``pose`` (4x4, NaN when failed), fitness, time, convergence."""

    pose: np.ndarray
    inlier_ratio: float
    rmse_m: float
    seconds: float
    converged: bool
    iterations: int

    @property
    def ok(self) -> bool:
        return bool(np.isfinite(self.pose).all())


def failed(seconds: float = 0.0) -> Registration:
    return Registration(np.full((4, 4), np.nan), float("nan"), float("nan"), seconds, False, 0)


def initial_guess(pose: np.ndarray | None) -> np.ndarray:
    """The starting pose of a registration (rules in the module docstring)."""
    T = np.eye(4)
    if pose is None:
        return T
    pose = np.asarray(pose, dtype=np.float64)
    if np.isfinite(pose[:3, :3]).all():
        T[:3, :3] = pose[:3, :3]
        if np.isfinite(pose[:3, 3]).all():
            T[:3, 3] = pose[:3, 3]
    return T


class PreparedScan:
    """A scan downsampled and made ready for registration (with its k-d tree)."""

    def __init__(self, points: np.ndarray, settings: RegistrationSettings):
        sg = _library()
        pts = np.asarray(points, dtype=np.float64)[:, :3]
        pts = pts[np.isfinite(pts).all(axis=1)]
        started = time.perf_counter()
        if len(pts) >= MIN_POINTS:
            self.cloud, self.tree = sg.preprocess_points(
                pts, downsampling_resolution=settings.voxel_m,
                num_neighbors=settings.neighbours, num_threads=settings.threads)
            self.points = np.asarray(self.cloud.points())[:, :3]
        else:
            self.cloud = self.tree = None
            self.points = np.empty((0, 3))
        self.kdtree = cKDTree(self.points) if len(self.points) >= MIN_POINTS else None
        self.seconds = time.perf_counter() - started

    @property
    def usable(self) -> bool:
        return self.kdtree is not None


def fitness(source: np.ndarray, target_tree: cKDTree, T: np.ndarray,
            inlier_m: float) -> tuple[float, float]:
    """``(inlier_ratio, rmse_m)`` of ``source`` moved by ``T`` against the target tree."""
    if len(source) == 0 or not np.isfinite(T).all():
        return float("nan"), float("nan")
    moved = source @ T[:3, :3].T + T[:3, 3]
    dist, _ = target_tree.query(moved, k=1, distance_upper_bound=inlier_m)
    inliers = np.isfinite(dist)
    ratio = float(np.count_nonzero(inliers) / len(source))
    rmse = float(np.sqrt(np.mean(dist[inliers] ** 2))) if inliers.any() else float("nan")
    return ratio, rmse


def register(target: PreparedScan, source: PreparedScan, initial: np.ndarray,
             settings: RegistrationSettings) -> Registration:
    """Align ``source`` to ``target`` from ``initial`` (``T_target_source``)."""
    if not (target.usable and source.usable):
        return failed()
    sg = _library()
    started = time.perf_counter()
    result = sg.align(target.cloud, source.cloud, target.tree,
                      init_T_target_source=np.asarray(initial, dtype=np.float64),
                      registration_type=settings.method.upper(),
                      max_correspondence_distance=settings.max_correspondence_m,
                      num_threads=settings.threads, max_iterations=settings.max_iterations)
    seconds = time.perf_counter() - started
    T = np.array(result.T_target_source, dtype=np.float64)
    if not np.isfinite(T).all():
        return failed(seconds)
    ratio, rmse = fitness(source.points, target.kdtree, T, settings.inlier_m)
    return Registration(T, ratio, rmse, seconds, bool(result.converged), int(result.iterations))


def register_points(target_points: np.ndarray, source_points: np.ndarray,
                    initial: np.ndarray | None = None,
                    settings: RegistrationSettings | None = None) -> Registration:
    """Register two raw point arrays (``(N, 3+)``): :func:`register` after preparing both."""
    settings = (settings or RegistrationSettings()).check()
    return register(PreparedScan(target_points, settings), PreparedScan(source_points, settings),
                    initial_guess(initial), settings)


@dataclass(frozen=True)
class RefinedPoses:
    """Registrations of many pairs, one row each (NaN rows where not registered).

    ``pose (Q, 4, 4)``, ``inlier_ratio``, ``rmse_m``, ``seconds`` (alignment
    wall time), ``converged``; ``prepare_s`` is the total downsampling time of the
    call that registered them (:func:`refine_many`: shared by its passes).
    """

    pose: np.ndarray
    inlier_ratio: np.ndarray
    rmse_m: np.ndarray
    seconds: np.ndarray
    converged: np.ndarray
    prepare_s: float
    settings: RegistrationSettings

    @property
    def registered(self) -> np.ndarray:
        return np.isfinite(self.pose).all(axis=(1, 2))


#: prepared scans a cache holds (about 5 MB each at 16k downsampled points, small-mixed;
#: 128 keep the serial plan at one preparation per scan there, and under 2 GB at KITTI scale)
CACHE_SCANS = 128
#: prepared scans each pool worker keeps (an LRU: it does not know its next tasks)
WORKER_CACHE_SCANS = 64


class ScanCache:
    """Prepared scans of a sequence: the most recent ``size`` frames, or by a known plan.

    Without a plan the cache is an LRU. :meth:`plan` gives the order in which
    scans will be asked for (the serial registration knows all its loops in
    advance): a scan is then dropped after its last use, and when more than
    ``size`` are still needed later the one needed furthest ahead goes first
    (Belady's rule), so each scan is prepared once whenever ``size`` allows
    (small-mixed, 370 loops: 400 preparations for 400 scans at 128, against 549 by
    an LRU of 128 and 445 by one of 256).
    """

    def __init__(self, sequence, settings: RegistrationSettings, size: int = CACHE_SCANS):
        self.sequence = sequence
        self.settings = settings
        self.size = size
        self._items: OrderedDict[int, PreparedScan] = OrderedDict()
        self.prepare_s = 0.0
        self.n_prepared = 0  # scans downsampled so far (a scan evicted and met again counts twice)
        self._uses: dict[int, deque] | None = None
        self._clock = 0

    def plan(self, accesses) -> None:
        """Scans in the order they will be asked for (replaces any earlier plan)."""
        self._uses = {}
        for t, index in enumerate(accesses):
            self._uses.setdefault(int(index), deque()).append(t)
        self._clock = 0

    def _next_use(self, index: int) -> float:
        uses = self._uses.get(index) if self._uses is not None else None
        return uses[0] if uses else float("inf")

    def __getitem__(self, index: int) -> PreparedScan:
        index = int(index)
        if index in self._items:
            self._items.move_to_end(index)
            scan = self._items[index]
        else:
            scan = PreparedScan(self.sequence[index], self.settings)
            self.prepare_s += scan.seconds
            self.n_prepared += 1
            self._items[index] = scan
        if self._uses is None:
            if len(self._items) > self.size:
                self._items.popitem(last=False)
            return scan
        uses = self._uses.get(index)
        while uses and uses[0] <= self._clock:  # this access, and any the caller skipped
            uses.popleft()
        self._clock += 1
        if not uses:  # never asked for again
            del self._items[index]
        elif len(self._items) > self.size:
            del self._items[max(self._items, key=self._next_use)]
        return scan


def has_points(sequence) -> bool:
    """False for sequences whose scans are not point clouds (the GOSMatch object layout)."""
    return not getattr(sequence, "has_objects", False)


#: most loops in one parallel task (a chunk shares its prepared scans)
CHUNK_LOOPS = 24


def _register_chunk(sequence, settings: RegistrationSettings, query: np.ndarray,
                    match: np.ndarray, initial: np.ndarray, cache: ScanCache | None = None):
    """Register ``match[k]`` to ``query[k]`` from ``initial[k]`` for every ``k`` (one task).

    Each scan is prepared once per process (:class:`ScanCache`, kept across the
    tasks a pool worker runs). Returns the per-row arrays and the preparation
    time and count spent here.
    """
    if cache is None:
        cache = _process_cache(sequence, settings)
    before_s, before_n = cache.prepare_s, cache.n_prepared
    n = len(query)
    pose = np.full((n, 4, 4), np.nan)
    ratio, rmse, secs = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
    conv = np.zeros(n, dtype=bool)
    for k in range(n):
        r = register(cache[query[k]], cache[match[k]], initial[k], settings)
        pose[k], ratio[k], rmse[k], secs[k], conv[k] = (r.pose, r.inlier_ratio, r.rmse_m,
                                                        r.seconds, r.converged)
    return (pose, ratio, rmse, secs, conv, cache.prepare_s - before_s,
            cache.n_prepared - before_n)


#: the scan cache of a pool worker (one sequence and settings per pool)
_PROCESS_CACHE: dict[tuple[int, RegistrationSettings], ScanCache] = {}


def _process_cache(sequence, settings: RegistrationSettings) -> ScanCache:
    key = (id(sequence), settings)
    if key not in _PROCESS_CACHE:
        _PROCESS_CACHE.clear()
        _PROCESS_CACHE[key] = ScanCache(sequence, settings, WORKER_CACHE_SCANS)
    return _PROCESS_CACHE[key]


def _chunks(order: np.ndarray, n_workers: int) -> list[np.ndarray]:
    """Cut the sorted rows into tasks of at most :data:`CHUNK_LOOPS`."""
    size = int(np.clip(np.ceil(len(order) / max(1, 4 * n_workers)), 1, CHUNK_LOOPS))
    return [order[i:i + size] for i in range(0, len(order), size)]


def refine_many(sequence, passes: list[tuple[np.ndarray, np.ndarray, np.ndarray | None]],
                settings: RegistrationSettings | None = None,
                progress: Callable[[int], object] | None = None,
                cache: ScanCache | None = None, executor=None) -> list[RefinedPoses]:
    """:func:`refine_pairs` for several passes ``(query, match, initial)`` at once.

    The rows of every pass with ``match >= 0`` are sorted by query scan (by
    match scan on workers) and cut into tasks; with an ``executor`` that runs several
    tasks at once (``concurrency() > 1``:
    :meth:`~lidar_iris_eval.executor.SerialExecutor.imap`) the tasks run
    in parallel, each worker preparing a scan once and reusing it for every
    loop it registers with that scan. Every registration is a pure function
    of the two scans and its initial pose, so the poses are the serial ones
    (single-threaded ``small_gicp``), and a row repeating another's pair and
    start (in another pass: two methods' passes in one call) takes its result
    (and its ``seconds``) instead of registering again. ``progress`` ticks
    once per row and pass.
    """
    settings = (settings or RegistrationSettings()).check()
    if not has_points(sequence):
        raise LirisError(option("refine", settings.method),
                         "this sequence has objects, not point clouds; nothing to register")
    _library()
    queries, matches, starts, owner = [], [], [], []
    sizes = []
    for p, (query, match, initial) in enumerate(passes):
        query = np.asarray(query, dtype=np.int64)
        match = np.asarray(match, dtype=np.int64)
        sizes.append(len(query))
        rows = np.flatnonzero(match >= 0)
        queries.append(query[rows])
        matches.append(match[rows])
        starts.append(np.stack([initial_guess(None if initial is None else initial[k])
                                for k in rows]) if len(rows) else np.empty((0, 4, 4)))
        owner.append(np.stack([np.full(len(rows), p), rows], axis=1))
    query = np.concatenate(queries) if queries else np.empty(0, np.int64)
    match = np.concatenate(matches) if matches else np.empty(0, np.int64)
    start = np.concatenate(starts) if starts else np.empty((0, 4, 4))
    owner = np.concatenate(owner) if owner else np.empty((0, 2), np.int64)
    out = [{"pose": np.full((n, 4, 4), np.nan), "ratio": np.full(n, np.nan),
            "rmse": np.full(n, np.nan), "secs": np.full(n, np.nan),
            "conv": np.zeros(n, dtype=bool)} for n in sizes]
    if progress is not None:  # rows without a match count as done
        skipped = sum(sizes) - len(query)
        if skipped:
            progress(skipped)
    # the same pair from the same start (two methods without a pose: both the identity) is
    # registered once: the result is a function of (query, match, start) alone
    first: dict[tuple, int] = {}
    unique = np.array([first.setdefault((int(a), int(b), t.tobytes()), r)
                       for r, (a, b, t) in enumerate(zip(query, match, start, strict=True))],
                      dtype=np.int64)
    rows_of: dict[int, list[int]] = {}
    for r, u in enumerate(unique):
        rows_of.setdefault(int(u), []).append(r)
    todo = np.array(sorted(rows_of), dtype=np.int64)
    workers = 1 if executor is None else executor.concurrency()
    parallel = workers > 1  # else here, sharing ``cache`` (nothing to gain from shipping)
    # serial: by query (the planned cache then prepares each scan once); workers: by match,
    # so the loops of one match scan sit in one task (small-mixed, 370 loops, 2 workers with
    # an LRU of 64: 522 preparations for 400 scans, against 602 by query)
    keys = (query[todo], match[todo]) if parallel else (match[todo], query[todo])
    order = todo[np.lexsort(keys)]
    chunks = _chunks(order, workers if parallel else 1)
    prepare_s, n_prepared = 0.0, 0
    cache = cache if cache is not None else ScanCache(sequence, settings)
    tasks = [(query[c], match[c], start[c]) for c in chunks]
    if parallel:
        results = executor.imap(_register_chunk, tasks, shared=(sequence, settings))
    else:  # every access is known: each scan prepared once (ScanCache.plan)
        cache.plan(np.stack([query[order], match[order]], axis=1).ravel())
        results = ((i, _register_chunk(sequence, settings, *task, cache))
                   for i, task in enumerate(tasks))
    for index, (pose, ratio, rmse, secs, conv, chunk_s, chunk_n) in results:
        ticks = 0
        for j, u in enumerate(chunks[index]):
            for p, row in owner[rows_of[int(u)]]:
                o = out[p]
                o["pose"][row], o["ratio"][row], o["rmse"][row] = pose[j], ratio[j], rmse[j]
                o["secs"][row], o["conv"][row] = secs[j], conv[j]
                ticks += 1
        prepare_s += chunk_s
        n_prepared += chunk_n
        if progress is not None:
            progress(ticks)
    if parallel:  # the workers prepared the scans: count them in the caller's cache
        cache.prepare_s += prepare_s
        cache.n_prepared += n_prepared
    return [RefinedPoses(o["pose"], o["ratio"], o["rmse"], o["secs"], o["conv"], prepare_s,
                         settings) for o in out]


def refine_pairs(sequence, query: np.ndarray, match: np.ndarray, initial: np.ndarray | None,
                 settings: RegistrationSettings | None = None,
                 progress: Callable[[int], object] | None = None,
                 cache: ScanCache | None = None, executor=None) -> RefinedPoses:
    """Register scan ``match[k]`` to scan ``query[k]`` for every row with ``match >= 0``.

    ``initial`` ``(Q, 4, 4)`` holds the starting poses (any NaN handled by
    :func:`initial_guess`), or None for the identity everywhere. ``executor``:
    see :func:`refine_many`.
    """
    return refine_many(sequence, [(query, match, initial)], settings, progress, cache,
                       executor)[0]
