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
objects get ``seq.scan(i)``. Their inputs are checked against the sequence
before any work (:meth:`Descriptor.check_inputs`).
"""

from __future__ import annotations

import functools
import hashlib
import os
import sys
import time
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lidar_iris_eval import __version__
from lidar_iris_eval.cache import CacheKey, DescriptorCache
from lidar_iris_eval.config import params_dict
from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.features import RaggedFeatures
from lidar_iris_eval.errors import LirisError, option

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
    from_cache : True when nothing was computed in this call.
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
    (a plug-in sub-package: helpers included), else its own file.
    """
    module = sys.modules.get(type(descriptor).__module__)
    own = getattr(module, "__file__", None)
    return _source_hash(str(Path(own).resolve()) if own else "")


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
    )


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
    if executor is not None:
        workers = executor.workers
    if workers < 1:
        raise LirisError(option("workers", workers), "must be at least 1")
    if chunk_size < 1:
        raise ValueError("chunk_size must be positive")
    if cache is not None and not isinstance(cache, DescriptorCache):
        cache = DescriptorCache(cache)
    descriptor.check_inputs(seq)
    fingerprint = seq.fingerprint()
    key = cache_key(seq, descriptor, fingerprint)
    meta = dict(
        descriptor=descriptor.name,
        preset=getattr(descriptor, "preset", "custom"),
        params=params_dict(descriptor.params),
        sequence=seq.name,
        fingerprint=fingerprint,
        cache_path=cache.path(key) if cache is not None else None,
    )
    if cache is not None:
        stored = cache.load(key)
        if stored is not None and _complete(stored, len(seq)):
            _warn_if_degenerate(stored, descriptor, seq)
            return DescriptorDB(**meta, **_split(stored), from_cache=True)

    if cache is not None and not cache.writable(key):
        meta["cache_path"] = None  # someone else's unreadable file: compute, do not store
    elif cache is not None:
        cache.check_writable()  # fail now, not after the extraction
    chunks = cache.load_chunks(key) if cache is not None else {}
    ranges = chunk_ranges(len(seq), chunk_size)
    joined = _Joiner(ranges, descriptor.name)
    for (a, b), arrays in chunks.items():  # resumed from a killed run
        if (a, b) in ranges:
            joined.add(a, b, arrays)
    del chunks
    todo = [r for r in ranges if r not in joined]
    bar = tqdm(total=len(seq), initial=len(seq) - sum(b - a for a, b in todo),
               desc=descriptor.name, unit="scan", file=sys.stderr, disable=not progress,
               leave=False)
    with bar:
        for (a, b), arrays in _compute_chunks(seq, descriptor, todo, workers, bar, executor):
            if cache is not None:
                cache.store_chunk(key, a, b, arrays)
            joined.add(a, b, arrays)
    arrays = joined.arrays()
    if cache is not None:
        cache.store(key, arrays)
    _warn_if_degenerate(arrays, descriptor, seq)
    return DescriptorDB(**meta, **_split(arrays), from_cache=False)


def _warn_if_degenerate(arrays, descriptor, seq) -> None:
    """Warn when most descriptors are empty or constant (millimetres, wrong frame)."""
    from lidar_iris_eval.descriptors.sanity import warn_if_degenerate

    warn_if_degenerate(arrays.get("descriptors"), descriptor.name, seq.name,
                       sample=lambda i: seq[i])


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


def _compute_chunks(seq, descriptor, todo, workers, bar, executor=None) -> Iterable:
    """Yield ``((a, b), arrays)`` for each range in ``todo`` (any order with a pool).

    With an executor that distributes work (Dask, ``--scheduler``), the chunks
    are its tasks.
    """
    if executor is not None and executor.distributes_blocks and todo:
        for index, arrays in executor.imap(_compute_range, todo, shared=(seq, descriptor)):
            a, b = todo[index]
            arrays = _raise_errors(arrays)
            bar.update(b - a)
            yield (a, b), arrays
        return
    if workers == 1 or len(todo) <= 1:
        for a, b in todo:
            yield (a, b), _raise_errors(_compute_range(seq, descriptor, a, b, bar.update))
        return
    with ProcessPoolExecutor(
        max_workers=min(workers, len(todo)),
        initializer=_init_worker,
        initargs=(seq, descriptor, os.getpid()),
    ) as pool:
        futures = {pool.submit(_worker_range, a, b): (a, b) for a, b in todo}
        try:
            for future in as_completed(futures):
                a, b = futures[future]
                arrays = _raise_errors(future.result())
                bar.update(b - a)
                yield (a, b), arrays
        except BaseException:
            for future in futures:
                future.cancel()
            raise


def _compute_range(seq, descriptor, a: int, b: int, tick=None):
    """Descriptors of scans ``[a, b)``; a LirisError is returned, not raised.

    Returning it keeps the error intact across a process boundary (its
    two-argument constructor does not survive pickling).
    """
    outputs, extract_s, read_s = [], np.empty(b - a), np.empty(b - a)
    wants_scan = descriptor.wants_scan()
    try:
        for k, i in enumerate(range(a, b)):
            t0 = time.perf_counter()
            if wants_scan:
                scan = seq.scan(i)
                t1 = time.perf_counter()
                _warm_up(descriptor, scan, wants_scan)
                c1 = time.thread_time()
                out = descriptor.describe(scan)
            else:  # bare points, exactly as compute(points) always got them
                points = seq[i]
                t1 = time.perf_counter()
                _warm_up(descriptor, points, wants_scan)
                c1 = time.thread_time()
                out = descriptor.compute(points)
            outputs.append(out if isinstance(out, dict) else np.asarray(out))
            c2 = time.thread_time()
            read_s[k], extract_s[k] = t1 - t0, c2 - c1
            if tick is not None:
                tick(1)
    except LirisError as err:
        return ("error", err.source, err.problem)
    times = {"extract_s": extract_s, "read_s": read_s}
    if outputs and isinstance(outputs[0], dict):
        if not all(isinstance(o, dict) for o in outputs):
            raise RuntimeError(f"{descriptor.name}.compute returned a feature set for some "
                               "scans and an array for others")
        features = RaggedFeatures.from_list(outputs, f"{descriptor.name}.compute")
        return {**features.to_arrays(), **times}
    return {"descriptors": np.stack(outputs), **times}


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


def _raise_errors(result):
    if isinstance(result, tuple):
        _, source, problem = result
        raise LirisError(source, problem)
    return result


# Per-process state of pool workers: set once by the initializer, so each task
# only ships two integers instead of the sequence and descriptor.
_WORKER: dict[str, Any] = {}


def _init_worker(seq, descriptor, parent_pid: int | None = None) -> None:
    if parent_pid is not None:  # a SIGKILLed liris must not leave workers computing
        from lidar_iris_eval.lifetime import die_with_parent

        die_with_parent(parent_pid)
    _WORKER["seq"], _WORKER["descriptor"] = seq, descriptor


def _worker_range(a: int, b: int):
    return _compute_range(_WORKER["seq"], _WORKER["descriptor"], a, b)


def external_database(desc, seq_name: str = "", fingerprint: str = ""):
    """A :class:`DescriptorDB` for an
    :class:`~lidar_iris_eval.descriptors.external.ExternalDescriptor`, as extraction returns.

    Times are NaN: the descriptors were computed elsewhere, so their cost is
    unknown and is reported as undefined.
    """
    stacked = desc.stacked()
    n = len(stacked)
    return DescriptorDB(descriptor=desc.name, preset=desc.preset, params=params_dict(desc.params),
                        descriptors=stacked, extract_s=np.full(n, np.nan),
                        read_s=np.full(n, np.nan), sequence=seq_name, fingerprint=fingerprint,
                        cache_path=None, from_cache=False)
