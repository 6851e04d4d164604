"""Extraction pipeline: a sequence x a descriptor -> stacked descriptors + per-scan times.

::

    db = extract(seq, get_descriptor("m2dp"), cache=DescriptorCache(".liris-cache"))
    db.descriptors      # (N, ...) array (record array for multi-part descriptors),
                        # or RaggedFeatures when compute returns variable-size feature sets
    db.extract_s        # (N,) seconds spent in descriptor.compute per scan

Scans are processed in fixed chunks (``chunk_size`` scans). With a cache each
finished chunk is stored at once, so a killed run resumes from its last chunk,
and the complete array is stored as one verified file at the end. A second call
with the same inputs loads that file and computes nothing.

For a method whose rows depend on their own scan alone (``Descriptor.per_frame``:
LiDAR Iris, Scan Context, M2DP, ESF), a frame selection that misses the cache
takes the rows of the scans it shares with a cached run of another selection
(``--frames 0:100`` after a run on all frames) from that run's file, chunk by
chunk, instead of computing them (cache.py, row index); the rows are bitwise
those a fresh extraction gives. Local-map methods never do: their rows depend
on the frames kept.

``workers > 1`` spreads chunks over a local process pool. ``extract_s`` is the
CPU time of the calling thread (:func:`time.thread_time`) spent in
``descriptor.compute``: processes competing for cores (``--workers 8`` on two
cores, a shared machine) do not inflate it, as wall time would (2,331 ms
against 14.6 ms per scan measured). Each process first runs the descriptor
once on its first scan, untimed, so numba compilation (or loading numba's
cache) is not reported as descriptor cost (a descriptor class with nothing to
compile may set ``warm_up = False`` to skip that extra call). Reading the scan (``read_s``) is
wall time: it is mostly waiting for the disk.

Each scan goes through :meth:`Descriptor.describe`: point descriptors get the
bare points (``seq[i]``, as always), methods that read labels, intensity or
objects get the scan with what their ``inputs`` declare (``Sequence.read``: a
label file is read only for a method that declares ``labels``). Their inputs
are checked against the sequence before any work (:meth:`Descriptor.check_inputs`).
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lidar_iris_eval import __version__
from lidar_iris_eval.cache import CacheKey, DescriptorCache, input_fingerprint, scan_identities
from lidar_iris_eval.config import params_dict
from lidar_iris_eval.descriptors.base import Descriptor, reads_local_maps, shares_rows
from lidar_iris_eval.descriptors.features import RaggedFeatures
from lidar_iris_eval.errors import LirisError, option
from lidar_iris_eval.io.scans import Scan
from lidar_iris_eval.io.sequence import read_scan

DEFAULT_CHUNK_SIZE = 50


@dataclass(frozen=True)
class DescriptorDB:
    """The descriptors of one sequence, with what produced them.

    Attributes
    ----------
    descriptor, preset, params : the descriptor's registry name, preset and
        full parameter dict.
    descriptors : ``(N, ...)`` stacked output of ``compute``, or
        :class:`RaggedFeatures` when ``compute`` returns feature sets.
    extract_s, read_s : ``(N,)`` seconds per scan spent in ``compute`` and in
        reading the scan file (from the run that computed them).
    sequence, fingerprint : the sequence name and content fingerprint.
    cache_path : the cache file, or None when no cache was used.
    from_cache : True when nothing was computed in this call (loaded from its own
        file, or every row taken from the file of another frame selection).
    reused_rows : scans whose rows were taken from another frame selection's
        cached file (see the module docstring) rather than computed; 0 otherwise.
    warnings : the warnings that qualify results computed from these descriptors
        (degenerate descriptors, :mod:`lidar_iris_eval.descriptors.sanity`); the
        run stores them with each result row.
    """

    descriptor: str
    preset: str
    params: dict[str, Any]
    descriptors: np.ndarray | RaggedFeatures
    extract_s: np.ndarray
    read_s: np.ndarray
    sequence: str
    fingerprint: str
    cache_path: Path | None
    from_cache: bool
    warnings: tuple[str, ...] = ()
    reused_rows: int = 0

    def __len__(self) -> int:
        return len(self.descriptors)

    @property
    def extract_ms_per_scan(self) -> float:
        """Mean ``compute`` time per scan in milliseconds."""
        return float(np.mean(self.extract_s) * 1e3) if len(self.extract_s) else float("nan")


def descriptor_code_hash(descriptor: Descriptor) -> str:
    """SHA-256 of the source files that can change ``descriptor``'s output.

    A method is a sub-package of ``lidar_iris_eval.descriptors`` (its
    descriptor, kernels and helpers side by side), so the hash covers every
    ``.py`` file of the package folder that holds the descriptor's module,
    sub-folders included, plus the shared modules directly in
    ``descriptors/`` (base class, common helpers). A descriptor defined
    elsewhere hashes its own package folder when its module sits in a package
    (a plug-in sub-package: helpers included), else its own file. A descriptor
    with a ``cache_token()`` method (a checksum of data files it reads, such as
    learned weights) appends it.
    """
    module = sys.modules.get(type(descriptor).__module__)
    own = getattr(module, "__file__", None)
    code = _source_hash(str(Path(own).resolve()) if own else "")
    if reads_local_maps(descriptor):  # the local maps it reads are built by our code
        from lidar_iris_eval.localmaps.extraction import local_map_code_hash

        code = f"{code}+{local_map_code_hash()}"
    token = getattr(descriptor, "cache_token", None)
    if token is not None:  # data the output depends on besides the code (e.g. ESM's weights)
        code = f"{code}+{token()}"
    return code


@functools.cache
def _source_hash(module_file: str) -> str:
    """Hash once per process, so the key describes the code this process runs
    even if a file is edited while it works."""
    files: set[Path] = set()
    if module_file:
        own = Path(module_file)
        package = Path(__file__).resolve().parent / "descriptors"
        folder = own.parent
        if folder.parent == package:  # a method's sub-package: all of it
            files.update(p.resolve() for p in folder.rglob("*.py"))
            files.update(p.resolve() for p in package.glob("*.py"))
        elif folder == package:
            files.update(p.resolve() for p in package.glob("*.py"))
        elif (folder / "__init__.py").is_file():  # a plug-in package outside ours
            files.update(p.resolve() for p in folder.rglob("*.py"))
        files.add(own)
    digest = hashlib.sha256()
    for path in sorted(files):
        digest.update(str(path.name).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def cache_key(seq, descriptor: Descriptor, fingerprint: str | None = None) -> CacheKey:
    """The cache key of ``descriptor`` on ``seq`` (parameters, version, code, scan fingerprint).

    The version includes NumPy's: ESF draws its triplets from NumPy's random
    generator, whose streams NumPy does not promise to keep across releases.
    """
    return CacheKey.build(
        sequence="scans",  # not seq.name: a copied or renamed data set must hit the cache
        # (the fingerprint already identifies the scans; issue 15)
        fingerprint=fingerprint if fingerprint is not None else seq.fingerprint(),
        descriptor=descriptor.name,
        params=params_dict(descriptor.params),
        version=f"{__version__}+numpy-{np.__version__}",
        n_scans=len(seq),
        code=descriptor_code_hash(descriptor),
        inputs=_inputs_key(seq, descriptor),
    )


def _read_inputs(descriptor) -> frozenset[str]:
    """What to read for ``descriptor``: its declared and its optional inputs."""
    read = getattr(descriptor, "read_inputs", None)
    return read() if read is not None else frozenset(getattr(descriptor, "inputs", ()))


def _inputs_key(seq, descriptor: Descriptor) -> str:
    """The inputs beyond the scans: labels (cache.input_fingerprint) and, for a method
    reading local maps, what its poses depend on (odometry.odometry_key: the GT poses'
    hash with ``gt``, KISS-ICP's version and settings with ``kiss-icp``)."""
    key = input_fingerprint(seq, _read_inputs(descriptor))
    if reads_local_maps(descriptor) and hasattr(descriptor, "local_map_settings"):
        from lidar_iris_eval.localmaps.odometry import odometry_key

        odometry = odometry_key(seq, descriptor.local_map_settings().odometry)
        key = f"{key};{odometry}" if key else odometry
    return key


def chunk_ranges(n: int, size: int) -> list[tuple[int, int]]:
    """Fixed ``[start, stop)`` ranges; fixed so a resumed run finds the same chunks."""
    return [(a, min(a + size, n)) for a in range(0, n, size)]


def extract(
    seq,
    descriptor: Descriptor,
    cache: DescriptorCache | str | os.PathLike | None = None,
    workers: int = 1,
    progress: bool = False,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    executor=None,
) -> DescriptorDB:
    """Compute (or load) the descriptors of every scan of ``seq``.

    Parameters
    ----------
    seq : a :class:`~lidar_iris_eval.io.Sequence` (``len``, ``seq[i]``, ``name``,
        ``fingerprint()``).
    descriptor : the descriptor to run.
    cache : a :class:`DescriptorCache`, a cache folder, or None for no caching.
    workers : processes to use; 1 computes in this process.
    progress : show a tqdm bar on stderr.
    chunk_size : scans per chunk (unit of resumption and of pool tasks).
    executor : a :mod:`lidar_iris_eval.executor` executor built by the caller;
        its ``workers`` replace ``workers``, and one that distributes work
        (Dask) runs the chunks as its tasks.
    """
    (db,) = extract_many(seq, [descriptor], cache, workers, progress, chunk_size, executor)
    return db


@dataclass
class _Plan:
    """One descriptor of :func:`extract_many`: its cache key, metadata and joined chunks."""

    descriptor: Descriptor
    key: CacheKey
    meta: dict[str, Any]
    joined: _Joiner | None = None
    ready: DescriptorDB | None = None
    todo: tuple[tuple[int, int], ...] = ()
    reused: int = 0  # scans taken from another selection's file (_reuse_rows)


def extract_many(
    seq,
    descriptors: list[Descriptor],
    cache: DescriptorCache | str | os.PathLike | None = None,
    workers: int = 1,
    progress: bool = False,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    executor=None,
) -> list[DescriptorDB]:
    """:func:`extract` for several descriptors, reading and cleaning each scan once.

    Every scan still to compute is read once and handed to every descriptor
    that needs it (one read instead of one per descriptor: about 20 s of a
    full-resolution KITTI-00 run with four descriptors). Each descriptor keeps
    its own cache file, its own resumable chunks and its own ``extract_s``
    (thread CPU time of its ``compute`` alone); ``read_s`` is the shared read,
    the same value in every descriptor read together. Descriptors found
    complete in the cache are loaded and read nothing. Point descriptors get
    ``seq[i]`` and scan descriptors the scan with their declared inputs; a run
    mixing both kinds reads each scan once. Returns one :class:`DescriptorDB` per
    descriptor, in order; the results equal :func:`extract` of each.
    """
    if executor is not None:
        workers = executor.workers
    if workers < 1:
        raise LirisError(option("workers", workers), "must be at least 1")
    if chunk_size < 1:
        raise ValueError("chunk_size must be positive")
    if cache is not None and not isinstance(cache, DescriptorCache):
        cache = DescriptorCache(cache)
    for descriptor in descriptors:
        descriptor.check_inputs(seq)
    fingerprint = seq.fingerprint()
    ranges = chunk_ranges(len(seq), chunk_size)
    plans = [_plan(seq, d, cache, fingerprint, ranges) for d in descriptors]
    identities = _Identities(seq)
    for plan in plans if cache is not None else ():
        if plan.ready is None and plan.todo and plan.meta["cache_path"] is not None:
            _reuse_rows(plan, cache, identities)
        elif plan.ready is not None:
            _index_rows(plan, cache, identities)  # a file of an earlier release: index it
    pending = [p for p in plans if p.ready is None]
    # ranges -> the descriptors that still need them (usually every range, all of them)
    # (a local-map method reads the scans of its window itself: a group of its own)
    needs: dict[tuple[int, int], list[int]] = {}
    groups: dict[tuple[int, ...], list[tuple[int, int]]] = {}
    for index, plan in enumerate(pending):
        if reads_local_maps(plan.descriptor):
            groups[(index,)] = list(plan.todo)
            continue
        for r in plan.todo:
            needs.setdefault(r, []).append(index)
    for r in ranges:
        if r in needs:
            groups.setdefault(tuple(needs[r]), []).append(r)
    groups = {k: v for k, v in groups.items() if v}
    needs = {r: None for todo in groups.values() for r in todo}
    done = len(seq) - sum(b - a for a, b in needs)
    names = ",".join(p.descriptor.name for p in pending) or ",".join(d.name for d in descriptors)
    bar = tqdm(total=len(seq), initial=done, desc=names, unit="scan", file=sys.stderr,
               disable=not progress or not pending, leave=False)
    if needs and any(getattr(p.descriptor, "warm_up", True) is not False for p in pending):
        _say_warming_up(bar)
    with bar:
        for members, todo in groups.items():
            descs = [pending[i].descriptor for i in members]
            for d in descs if todo else ():
                if reads_local_maps(d):
                    _estimate_odometry(seq, d, progress)
            for (a, b), outputs in _compute_chunks(seq, descs, todo, workers, bar, executor):
                for i, arrays in zip(members, outputs, strict=True):
                    plan = pending[i]
                    if cache is not None:
                        cache.store_chunk(plan.key, a, b, arrays)
                    plan.joined.add(a, b, arrays)
    for plan in pending:
        arrays = plan.joined.arrays()
        if cache is not None and cache.store(plan.key, arrays) is not None:
            _index_rows(plan, cache, identities)
        found = _warn_if_degenerate(arrays, plan.descriptor, seq)
        reused_all = plan.reused > 0 and not plan.todo
        plan.ready = DescriptorDB(**plan.meta, **_split(arrays), from_cache=reused_all,
                                  warnings=found, reused_rows=plan.reused)
    return [p.ready for p in plans]


class _Identities:
    """The scans' content identities (cache.scan_identities), computed once per input set."""

    def __init__(self, seq):
        self.seq = seq
        self.memo: dict[frozenset[str], np.ndarray | None] = {}

    def __call__(self, reads: frozenset[str]) -> np.ndarray | None:
        if reads not in self.memo:
            self.memo[reads] = scan_identities(self.seq, reads)
        return self.memo[reads]


def _index_rows(plan: _Plan, cache: DescriptorCache, identities: _Identities) -> None:
    """Give ``plan``'s complete file its row index, when its method shares rows."""
    if not shares_rows(plan.descriptor):
        return
    reads = _read_inputs(plan.descriptor)
    family = plan.key.family(reads)
    if cache.has_rows(plan.key, family):
        return
    ids = identities(reads)
    if ids is not None:
        cache.store_rows(plan.key, family, ids)


def _reuse_rows(plan: _Plan, cache: DescriptorCache, identities: _Identities) -> None:
    """Fill ``plan``'s chunks from cached files of other frame selections, where they hold
    every scan of a chunk (same identity), and drop those chunks from ``plan.todo``.

    Only for methods that share rows (:func:`shares_rows`) and dense descriptors. Each
    file is loaded verified (checksum, key); the rows taken are the stored ones, so
    they are bitwise those a fresh extraction of the same scans gives.
    """
    if not shares_rows(plan.descriptor):
        return
    reads = _read_inputs(plan.descriptor)
    ids = identities(reads)
    if ids is None:
        return
    for other, rows in cache.find_rows(plan.key, plan.key.family(reads), ids):
        covered = [(a, b) for a, b in plan.todo if bool(np.all(rows[a:b] >= 0))]
        if not covered:
            continue
        stored = cache.load(other)
        if (stored is None or not _complete(stored, other.n_scans)
                or RaggedFeatures.in_arrays(stored)):
            continue
        for a, b in covered:
            take = rows[a:b]
            plan.joined.add(a, b, {name: stored[name][take]
                                   for name in ("descriptors", "extract_s", "read_s")})
            plan.reused += b - a
        plan.todo = tuple(r for r in plan.todo if r not in plan.joined)
        if not plan.todo:
            break


def _plan(seq, descriptor: Descriptor, cache, fingerprint: str, ranges) -> _Plan:
    """What is left to compute for ``descriptor``: nothing (complete in the cache) or chunks."""
    key = cache_key(seq, descriptor, fingerprint)
    meta = dict(
        descriptor=descriptor.name,
        preset=getattr(descriptor, "preset", "custom"),
        params=params_dict(descriptor.params),
        sequence=seq.name,
        fingerprint=fingerprint,
        cache_path=cache.path(key) if cache is not None else None,
    )
    plan = _Plan(descriptor, key, meta)
    if cache is not None:
        stored = cache.load(key)
        if stored is not None and _complete(stored, len(seq)):
            found = _warn_if_degenerate(stored, descriptor, seq)
            plan.ready = DescriptorDB(**meta, **_split(stored), from_cache=True, warnings=found)
            return plan
    if cache is not None and not cache.writable(key):
        meta["cache_path"] = None  # someone else's unreadable file: compute, do not store
    elif cache is not None:
        cache.check_writable()  # fail now, not after the extraction
    chunks = cache.load_chunks(key) if cache is not None else {}
    plan.joined = _Joiner(ranges, descriptor.name)
    for (a, b), arrays in chunks.items():  # resumed from a killed run
        if (a, b) in ranges:
            plan.joined.add(a, b, arrays)
    plan.todo = tuple(r for r in ranges if r not in plan.joined)
    return plan


def _say_warming_up(bar) -> None:
    """Until the first scan is done, the bar says why it sits at 0 %: the first call
    compiles the kernels (about 27 s for LiDAR Iris on a cold cache)."""
    bar.set_postfix_str("first scan: compiling kernels on a first run", refresh=True)
    update = bar.update

    def first_update(n=1):
        bar.update = update
        bar.set_postfix_str("", refresh=False)
        return update(n)

    bar.update = first_update


def _warn_if_degenerate(arrays, descriptor, seq) -> tuple[str, ...]:
    """Warn when most descriptors are empty or constant (millimetres, wrong frame);
    returns the warnings, which qualify every result of these descriptors."""
    from lidar_iris_eval.descriptors.sanity import recording_qualifiers, warn_if_degenerate

    with recording_qualifiers() as found:
        warn_if_degenerate(arrays.get("descriptors"), descriptor.name, seq.name,
                           sample=lambda i: seq[i])
    return tuple(entry["warning"] for entry in found)


def _complete(arrays: dict[str, np.ndarray], n: int) -> bool:
    names = {"extract_s", "read_s"}
    if not (names <= set(arrays) and all(len(arrays[k]) == n for k in names)):
        return False
    if RaggedFeatures.in_arrays(arrays):
        return RaggedFeatures.n_scans_in(arrays) == n
    return "descriptors" in arrays and len(arrays["descriptors"]) == n


def _split(arrays: dict[str, np.ndarray]) -> dict[str, Any]:
    out: dict[str, Any] = {k: arrays[k] for k in ("extract_s", "read_s")}
    if RaggedFeatures.in_arrays(arrays):
        out["descriptors"] = RaggedFeatures.from_arrays(arrays)
    else:
        out["descriptors"] = arrays["descriptors"]
    return out


class _Joiner:
    """The chunks of one extraction, joined as they arrive (in any order).

    Dense descriptors are copied at once into one preallocated ``(N, ...)``
    array, so each chunk is let go as soon as it is stored: the descriptors
    are held once. (Keeping every chunk until the end and concatenating them
    held them twice: 0.4 GiB more at 4541 LiDAR Iris frames.) Feature sets
    (ragged) are kept per chunk and joined at the end.
    """

    def __init__(self, ranges: list[tuple[int, int]], name: str):
        self.ranges, self.name = list(ranges), name
        self.times: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}
        self.ragged: dict[tuple[int, int], dict[str, np.ndarray]] = {}
        self.dense: np.ndarray | None = None

    def __contains__(self, chunk: tuple[int, int]) -> bool:
        return chunk in self.times

    def add(self, a: int, b: int, arrays: dict[str, np.ndarray]) -> None:
        """Store the arrays of scans ``[a, b)``."""
        ragged = RaggedFeatures.in_arrays(arrays)
        if (ragged and self.dense is not None) or (not ragged and self.ragged):
            raise RuntimeError(f"{self.name}.compute returned a feature set for some scans "
                               "and an array for others")
        if ragged:
            self.ragged[(a, b)] = arrays
        else:
            d = arrays["descriptors"]
            if self.dense is None:  # calloc: pages become memory as chunks are written
                self.dense = np.zeros((self.ranges[-1][1], *d.shape[1:]), dtype=d.dtype)
            elif d.dtype != self.dense.dtype or d.shape[1:] != self.dense.shape[1:]:
                raise RuntimeError(
                    f"{self.name}.compute returned inconsistent outputs: "
                    f"{self.dense.dtype}{self.dense.shape[1:]} vs {d.dtype}{d.shape[1:]}"
                )
            self.dense[a:b] = d
        self.times[(a, b)] = (arrays["extract_s"], arrays["read_s"])

    def arrays(self) -> dict[str, np.ndarray]:
        """Descriptors (or feature-set arrays) and per-scan times of every scan."""
        if not self.ranges:
            raise LirisError(self.name, "the sequence has no scans")
        times = {key: np.concatenate([self.times[r][k] for r in self.ranges])
                 for k, key in enumerate(("extract_s", "read_s"))}
        if self.dense is not None:
            return {"descriptors": self.dense, **times}
        try:
            features = RaggedFeatures.concatenate(
                [RaggedFeatures.from_arrays(self.ragged[r]) for r in self.ranges])
        except ValueError as err:
            raise RuntimeError(f"{self.name}.compute: inconsistent feature sets: {err}") from None
        return {**features.to_arrays(), **times}


def _compute_chunks(seq, descriptors, todo, workers, bar, executor=None) -> Iterable:
    """Yield ``((a, b), outputs)`` for each range in ``todo`` (any order with a pool).

    ``outputs`` holds one arrays dict per descriptor of ``descriptors``. The
    executor runs the chunks (``imap_progress``: in this process, its process
    pool or Dask tasks) and moves ``bar`` as far as it can see; without one,
    the local executor of ``workers``.
    """
    from lidar_iris_eval.executor import local_executor

    executor = local_executor(workers) if executor is None else executor
    # in this process the bar moves scan by scan; from a pool or cluster, chunk by chunk
    for index, outputs in executor.imap_progress(_compute_range, todo, (seq, descriptors),
                                                 tick=bar.update,
                                                 sizes=[b - a for a, b in todo]):
        yield todo[index], outputs


def _compute_range(seq, descriptors, a: int, b: int, tick=None):
    """Descriptors of scans ``[a, b)``, one arrays dict per descriptor; each scan read once.

    A bad scan is a LirisError naming it; it crosses a process boundary as
    raised (``LirisError`` pickles with its source and problem).
    """
    n = len(descriptors)
    outputs = [[] for _ in range(n)]
    extract_s = np.empty((n, b - a))
    read_s = np.empty(b - a)
    wants = [d.wants_scan() for d in descriptors]
    # read only what the methods declare (labels only for a method that uses them)
    inputs = frozenset().union(*(_read_inputs(d) for d, w in zip(descriptors, wants, strict=True)
                                 if w))
    i, name = a, descriptors[0].name if descriptors else "descriptor"
    try:
        if len(descriptors) == 1 and reads_local_maps(descriptors[0]):
            from lidar_iris_eval.localmaps.extraction import describe_local_maps

            outputs[0] = describe_local_maps(seq, descriptors[0], a, b, extract_s[0], read_s,
                                             tick, _warm_up)
        for k, i in enumerate(range(a, b) if not outputs[0] else ()):
            t0 = time.perf_counter()
            scan = read_scan(seq, i, inputs) if any(wants) else None
            if all(wants):
                points = None
            elif isinstance(scan, Scan):  # one read serves both kinds of method
                points = scan.points
            else:
                points = seq[i]
            t1 = time.perf_counter()
            for j, descriptor in enumerate(descriptors):
                name = descriptor.name
                if wants[j]:
                    _warm_up(descriptor, scan, True)
                    c1 = time.thread_time()
                    out = descriptor.describe(scan)
                else:  # bare points, exactly as compute(points) always got them
                    _warm_up(descriptor, points, False)
                    c1 = time.thread_time()
                    out = descriptor.compute(points)
                outputs[j].append(out if isinstance(out, dict) else np.asarray(out))
                extract_s[j, k] = time.thread_time() - c1
            read_s[k] = t1 - t0
            if tick is not None:
                tick(1)
    except LirisError as err:
        raise LirisError(scan_source(seq, i, err.source), err.problem) from None
    except MemoryError:
        raise LirisError(f"{name} parameters",
                         f"not enough memory to compute the descriptor of one scan "
                         f"({scan_source(seq, i, None)}); check --param / the preset's "
                         "sizes") from None
    return [_pack(d, outputs[j], extract_s[j], read_s.copy())
            for j, d in enumerate(descriptors)]


def _estimate_odometry(seq, descriptor, progress: bool) -> None:
    """Run the local maps' odometry once here, before any chunk (kiss-icp: memoised per
    process, so the chunks of this process, and pool workers forked from it, reuse it)."""
    if hasattr(descriptor, "local_map_settings"):
        from lidar_iris_eval.localmaps.odometry import estimate_odometry

        estimate_odometry(seq, descriptor.local_map_settings().odometry, progress)


def _pack(descriptor, outputs: list, extract_s: np.ndarray, read_s: np.ndarray) -> dict:
    """One descriptor's outputs of a range as the arrays its cache stores."""
    times = {"extract_s": extract_s, "read_s": read_s}
    if outputs and isinstance(outputs[0], dict):
        if not all(isinstance(o, dict) for o in outputs):
            raise RuntimeError(f"{descriptor.name}.compute returned a feature set for some "
                               "scans and an array for others")
        features = RaggedFeatures.from_list(outputs, f"{descriptor.name}.compute")
        return {**features.to_arrays(), **times}
    return {"descriptors": np.stack(outputs), **times}


def scan_source(seq, index: int, source: str | None) -> str | None:
    """A descriptor's complaint about its ``points`` named by the scan it came from."""
    if source not in (None, "points"):
        return source
    paths = getattr(seq, "scan_paths", None)
    if paths is not None and index < len(paths):
        return str(paths[index])
    return f"{getattr(seq, 'name', 'sequence')} scan {index}"


#: descriptors (class and parameters) already run once in this process
_WARMED: set[tuple[type, str]] = set()


def _warm_up(descriptor, scan, wants_scan: bool) -> None:
    """Run ``descriptor`` once on ``scan``, untimed, the first time in this process."""
    key = (type(descriptor), repr(getattr(descriptor, "params", None)))
    if key in _WARMED or getattr(descriptor, "warm_up", True) is False:
        return
    if wants_scan:
        descriptor.describe(scan)
    else:
        descriptor.compute(scan)
    _WARMED.add(key)


def external_database(desc, seq_name: str = "", fingerprint: str = ""):
    """A :class:`DescriptorDB` for an
    :class:`~lidar_iris_eval.descriptors.external.ExternalDescriptor`, as extraction returns.

    Times are NaN: the descriptors were computed elsewhere, so their cost is
    unknown and is reported as undefined.
    """
    from lidar_iris_eval.descriptors.sanity import recording_qualifiers, warn_if_degenerate

    stacked = desc.stacked()
    n = len(stacked)
    with recording_qualifiers() as found:
        if desc.params.kind == "vectors":
            # the same check as built-in descriptors get after extraction
            warn_if_degenerate(stacked, desc.name, seq_name or "external")
    return DescriptorDB(descriptor=desc.name, preset=desc.preset, params=params_dict(desc.params),
                        descriptors=stacked, extract_s=np.full(n, np.nan),
                        read_s=np.full(n, np.nan), sequence=seq_name, fingerprint=fingerprint,
                        cache_path=None, from_cache=False,
                        warnings=tuple(entry["warning"] for entry in found))
