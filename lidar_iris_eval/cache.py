"""A content-addressed descriptor cache: atomic writes, verified reads.

One file per (sequence, descriptor, parameters): ``<root>/<seq>-<descriptor>-<key>.npz``.
The key hashes everything that changes the stored numbers: the descriptor
name and its full parameter set, the package version, the sequence's content
fingerprint (:meth:`Sequence.fingerprint`) and a hash of the descriptor's
source code (so editing a descriptor between releases never serves stale
numbers). Anything else (the
sequence's path, the time of day) does not matter, so a copied dataset still
hits the cache.

Files are written to a temporary name in the same folder and moved into
place with :func:`os.replace`, so a reader sees either nothing or a complete
file, even when the writer is killed. Each file carries a SHA-256 of its arrays
and the key it was written for; a file that fails to load, or whose checksum
or key does not match, is reported with a warning, deleted, and treated as
missing, so the caller rebuilds it. A file this process may not read (another
user's, on a shared cache) is never deleted: it is reported, left in place,
and the descriptors are computed without caching them.

Files are created with the permissions the umask allows (``mkstemp`` alone
would make them private), so a group-shared cache stays shared.

Long extractions also store *chunks* (``<stem>.partial/chunk-<a>-<b>.npz``,
same format) as they go, so an interrupted run resumes where it stopped.

A method whose output for a scan depends on that scan alone
(``Descriptor.per_frame``) also gets a *row index* beside each complete file:
``<descriptor>-<family>.rows/<digest>.npz`` (same format) holds one content
identity per scan (:func:`scan_identities`: the scan file's name, size, mtime
and sampled bytes, plus its label file when the method reads labels). The
*family* (:meth:`CacheKey.family`) is the key without the sequence's
fingerprint and length, so two frame selections of one sequence (``--frames
0:400`` and ``--frames 100:200``) share it. A selection that misses the cache
takes the rows of its scans from a file of its family whose index holds the
same identities (:meth:`DescriptorCache.find_rows`), instead of computing
them again: the rows are those a fresh extraction gives, since each depends on
its scan alone and the scan's identity is the same. A scan whose file changed
has another identity, so its row is computed again. Methods whose rows depend
on other frames (local maps: ESM's local-map mode, MapClosures) get no index
and never share rows across selections.

Default location: ``$LIRIS_CACHE_DIR`` if set, else ``./.liris-cache`` in the
current directory (git-ignored in this repository).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidar_iris_eval.errors import LirisError, check_writable_dir, os_error, warn
from lidar_iris_eval.lifetime import remove_stale_temps, temp_prefix

CACHE_FORMAT = 2  # 2: extract_s is per-thread CPU time, compilation excluded
ROWS_FORMAT = 1  # the row index of per-frame methods (see the module docstring)
ENV_VAR = "LIRIS_CACHE_DIR"
DEFAULT_DIRNAME = ".liris-cache"
_META = "__meta__"


def umask() -> int:
    """The process umask (read by setting it and putting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def default_cache_dir() -> Path:
    """``$LIRIS_CACHE_DIR`` if set, else ``./.liris-cache``."""
    env = os.environ.get(ENV_VAR)
    return Path(env) if env else Path.cwd() / DEFAULT_DIRNAME


@dataclass(frozen=True)
class CacheKey:
    """What a cached array depends on; :meth:`digest` is its content address."""

    sequence: str
    fingerprint: str
    descriptor: str
    params: str  # canonical JSON of the parameter dict
    version: str
    n_scans: int
    code: str = ""  # hash of the descriptor source code (see extract.descriptor_code_hash)
    #: fingerprint of the inputs a method declares beyond the scan files (labels), see
    #: :func:`input_fingerprint`; "" for methods that read only the scan files
    inputs: str = ""

    @classmethod
    def build(
        cls,
        sequence: str,
        fingerprint: str,
        descriptor: str,
        params: dict[str, Any],
        version: str,
        n_scans: int,
        code: str = "",
        inputs: str = "",
    ) -> CacheKey:
        text = json.dumps(params, sort_keys=True, default=str)
        return cls(sequence, fingerprint, descriptor, text, version, int(n_scans), code,
                   inputs)

    def digest(self) -> str:
        fields = asdict(self)
        if not fields["inputs"]:
            del fields["inputs"]  # keys of scan-only methods stay those of earlier releases
        text = json.dumps({"format": CACHE_FORMAT, **fields}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:20]

    def stem(self) -> str:
        safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in self.sequence) or "seq"
        return f"{safe}-{self.descriptor}-{self.digest()}"

    def family(self, reads: Iterable[str]) -> str:
        """The key without the scans: what two frame selections of a sequence share.

        Everything of :meth:`digest` but the sequence fingerprint, the scan count
        and the whole-sequence input fingerprint, plus the names of the inputs
        read (``reads``): the per-scan identities (:func:`scan_identities`) stand
        for the scans instead, so a row is shared only between keys that agree
        on the method, its parameters, the versions and the code.
        """
        fields = asdict(self)
        for name in ("fingerprint", "n_scans", "inputs"):
            del fields[name]
        text = json.dumps({"format": CACHE_FORMAT, "rows": ROWS_FORMAT,
                           "reads": sorted(reads), **fields}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:20]


def arrays_checksum(arrays: dict[str, np.ndarray]) -> str:
    """SHA-256 over the names, dtypes, shapes and bytes of ``arrays``."""
    digest = hashlib.sha256()
    for name in sorted(arrays):
        arr = np.ascontiguousarray(arrays[name])
        digest.update(f"{name}|{arr.dtype.descr!r}|{arr.shape!r}|".encode())
        # the bytes in place (what tobytes() would copy: a second descriptor stack)
        digest.update(arr.reshape(-1).view(np.uint8))
    return digest.hexdigest()


def write_arrays(path: Path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    """Write ``arrays`` plus a checksummed JSON header to ``path`` atomically."""
    if _META in arrays:
        raise ValueError(f"array name {_META!r} is reserved")
    header = {**meta, "checksum": arrays_checksum(arrays)}
    blob = np.frombuffer(json.dumps(header, sort_keys=True).encode(), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=temp_prefix(path.name))
    try:
        os.fchmod(fd, 0o666 & ~umask())  # mkstemp makes 0600 whatever the umask
        with os.fdopen(fd, "wb") as handle:
            np.savez(handle, **arrays, **{_META: blob})
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except OSError as err:
        Path(tmp).unlink(missing_ok=True)
        raise os_error(err, path, "cannot write cache file") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_arrays(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read and verify a file written by :func:`write_arrays`.

    Raises
    ------
    ValueError
        When the file is truncated, not an archive, or fails its checksum.
    PermissionError
        When this process may not read it (not a sign of corruption).
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except PermissionError:
        raise
    except (zipfile.BadZipFile, OSError, EOFError, KeyError, ValueError) as err:
        raise ValueError(f"unreadable ({type(err).__name__}: {err})") from None
    blob = arrays.pop(_META, None)
    if blob is None:
        raise ValueError("no header")
    try:
        meta = json.loads(blob.tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise ValueError("corrupt header") from None
    if meta.get("checksum") != arrays_checksum(arrays):
        raise ValueError("checksum mismatch")
    return arrays, meta


def input_fingerprint(seq: Any, inputs: frozenset[str] | set[str]) -> str:
    """A fingerprint of the inputs in ``inputs`` that live outside the scan files.

    ``seq.fingerprint()`` covers the scan files (points and intensity) and, for
    object sequences, the object files. Per-point labels are separate files
    (``labels/*.label``): a method that declares ``"labels"`` gets them hashed
    here, the same way as the scans, so editing a label file never serves the
    descriptors computed from the old one. "" when nothing beyond the scans is read.
    """
    from lidar_iris_eval.io.sequence import hash_file_samples

    parts = []
    label_paths = getattr(seq, "label_paths", None)
    if "labels" in inputs and label_paths:
        digest = hashlib.sha256(b"labels;")
        hash_file_samples(digest, list(label_paths))
        parts.append(f"labels:{digest.hexdigest()[:16]}")
    return ";".join(parts)


#: the inputs a per-scan identity covers: the scan file (points, intensity) and its labels
_IDENTIFIED_INPUTS = frozenset({"points", "intensity", "labels"})
#: bytes of one scan identity (a truncated SHA-256)
IDENTITY_BYTES = 16


def scan_identities(seq: Any, inputs: frozenset[str] | set[str]) -> np.ndarray | None:
    """``(N, 16)`` uint8: one content identity per scan of ``seq``, or None.

    Each row hashes, as :meth:`Sequence.fingerprint` does for the whole
    sequence, the scan file's name, size, mtime and first and last 4 KiB
    (every byte inside ``full_scan_hashing``), plus the scan's label file when
    ``inputs`` holds ``"labels"``. The sequence fingerprint is a function of
    these files in order, so for a method whose rows depend on their own scan
    alone, equal identities mean equal rows.

    None when an identity would not cover what the rows depend on: a sequence
    type that reads or fingerprints its scans its own way (ROS bags, dataset
    readers, object sequences), or inputs beyond the scan and label files.
    """
    from lidar_iris_eval.io.sequence import Sequence, hash_file_samples

    if not isinstance(seq, Sequence) or not set(inputs) <= _IDENTIFIED_INPUTS:
        return None
    if any(getattr(type(seq), name) is not getattr(Sequence, name)
           for name in ("fingerprint", "scan", "read", "__getitem__")):
        return None
    labels = seq.label_paths if "labels" in inputs else None
    out = np.empty((len(seq), IDENTITY_BYTES), dtype=np.uint8)
    for i, path in enumerate(seq.scan_paths):
        digest = hashlib.sha256(b"scan;")
        hash_file_samples(digest, [path])
        if labels is not None:
            digest.update(b"labels;")
            hash_file_samples(digest, [labels[i]])
        out[i] = np.frombuffer(digest.digest()[:IDENTITY_BYTES], dtype=np.uint8)
    return out


def _identity_keys(ids: np.ndarray) -> list[bytes]:
    return [bytes(row) for row in np.ascontiguousarray(ids, dtype=np.uint8)]


class DescriptorCache:
    """Cache files under ``root``; see the module docstring for the layout."""

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root) if root is not None else default_cache_dir()
        if self.root.exists() and not self.root.is_dir():
            raise LirisError(self.root, "cache directory is a file")
        self._unreadable: set[Path] = set()  # other users' files: never replaced

    def __repr__(self) -> str:
        return f"DescriptorCache({str(self.root)!r})"

    def path(self, key: CacheKey) -> Path:
        return self.root / f"{key.stem()}.npz"

    def partial_dir(self, key: CacheKey) -> Path:
        return self.root / f"{key.stem()}.partial"

    def load(self, key: CacheKey) -> dict[str, np.ndarray] | None:
        """The arrays stored for ``key``, or None (a bad file is warned about and removed)."""
        return self._load_verified(self.path(key), key)

    def check_writable(self) -> None:
        """Raise a LirisError now (before any work) if the cache cannot be written.

        Also removes temporary files left by writers that were killed (their
        process is gone), so a SIGKILL leaves no debris for long.
        """
        check_writable_dir(self.root, "descriptor cache folder")
        remove_stale_temps(self.root)

    def writable(self, key: CacheKey) -> bool:
        """False when ``key``'s file exists but may not be read: it is left alone."""
        return self.path(key) not in self._unreadable

    def store(self, key: CacheKey, arrays: dict[str, np.ndarray]) -> Path | None:
        """Store the complete arrays for ``key`` and drop its partial chunks.

        Returns None (storing nothing) when the existing file is unreadable to
        this process: replacing it would destroy someone else's file.
        """
        path = self.path(key)
        if not self.writable(key):
            return None
        write_arrays(path, arrays, {"key": asdict(key), "digest": key.digest()})
        shutil.rmtree(self.partial_dir(key), ignore_errors=True)
        return path

    def store_chunk(
        self, key: CacheKey, start: int, stop: int, arrays: dict[str, np.ndarray]
    ) -> None:
        """Store the arrays of scans ``[start, stop)`` as one resumable chunk."""
        if not self.writable(key):
            return
        path = self.partial_dir(key) / f"chunk-{start:09d}-{stop:09d}.npz"
        meta = {"digest": key.digest(), "start": start, "stop": stop}
        try:
            write_arrays(path, arrays, meta)
        except (LirisError, OSError):
            with contextlib.suppress(OSError):  # a full disk leaves no empty folder behind
                path.parent.rmdir()
            raise

    def load_chunks(self, key: CacheKey) -> dict[tuple[int, int], dict[str, np.ndarray]]:
        """Verified chunks stored for ``key``, by ``(start, stop)``."""
        folder = self.partial_dir(key)
        chunks: dict[tuple[int, int], dict[str, np.ndarray]] = {}
        if not folder.is_dir():
            return chunks
        for path in sorted(folder.glob("chunk-*.npz")):
            try:
                _, a, b = path.stem.split("-")
                start, stop = int(a), int(b)
            except ValueError:
                continue
            # a chunk holds the rows its name says: its header records the range it was
            # written for, so a chunk copied or renamed over another is rejected
            arrays = self._load_verified(path, key, {"start": start, "stop": stop})
            if arrays is None:
                continue
            per_scan = [v for name, v in arrays.items() if not _flat_values(name)]
            if all(len(v) == stop - start for v in per_scan):
                chunks[(start, stop)] = arrays
        return chunks

    def rows_dir(self, key: CacheKey, family: str) -> Path:
        """The folder of ``family``'s row indexes (see the module docstring)."""
        safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in key.descriptor)
        return self.root / f"{safe}-{family}.rows"

    def has_rows(self, key: CacheKey, family: str) -> bool:
        """True when ``key``'s complete file already has its row index."""
        return (self.rows_dir(key, family) / f"{key.digest()}.npz").is_file()

    def store_rows(self, key: CacheKey, family: str, ids: np.ndarray) -> None:
        """Record the scan identities of ``key``'s complete file (one row each, in order).

        The index only saves work later, so failing to write it (a full disk, a
        folder of another user's) is a warning, never the end of a run whose
        descriptors are already stored. Temporary files of killed writers in the
        index folder are removed first, as :meth:`check_writable` does in the root.
        """
        if not self.writable(key):
            return
        folder = self.rows_dir(key, family)
        path = folder / f"{key.digest()}.npz"
        remove_stale_temps(folder)
        try:
            write_arrays(path, {"scan_ids": np.ascontiguousarray(ids, dtype=np.uint8)},
                         {"key": asdict(key), "digest": key.digest(), "family": family})
        except (LirisError, OSError) as err:
            warn(folder, f"cannot write the cache row index ({getattr(err, 'problem', err)}); "
                         "other frame selections will compute these scans again")

    def find_rows(self, key: CacheKey, family: str,
                  ids: np.ndarray) -> list[tuple[CacheKey, np.ndarray]]:
        """Other files of ``family`` holding rows of the scans ``ids``, best first.

        Returns ``(key, rows)`` pairs: ``rows[i]`` is the row of scan ``i`` in
        that key's file, -1 where it holds no scan of that identity; ordered by
        how many scans they cover. Each index is verified like a cache file
        (checksum, key and family); a bad one is warned about and deleted. The
        files themselves are verified again when loaded.
        """
        folder = self.rows_dir(key, family)
        if not folder.is_dir():
            return []
        wanted = _identity_keys(ids)
        found: list[tuple[int, CacheKey, np.ndarray]] = []
        for path in sorted(folder.glob("*.npz")):
            if path.stem == key.digest():
                continue
            try:
                arrays, meta = read_arrays(path)
                other = CacheKey(**meta["key"])
                if (meta.get("family") != family or meta.get("digest") != path.stem
                        or other.digest() != path.stem):
                    raise ValueError("written for a different key")
                stored = arrays["scan_ids"]
                if stored.ndim != 2 or stored.shape != (other.n_scans, IDENTITY_BYTES):
                    raise ValueError("not one identity per scan")
            except PermissionError:
                continue  # another user's index: not ours to delete, and unusable
            except (ValueError, KeyError, TypeError) as err:
                warn(path, f"corrupt cache row index ({err}); deleting it")
                path.unlink(missing_ok=True)
                continue
            if not self.path(other).is_file():
                path.unlink(missing_ok=True)  # its file was removed: the index is stale
                continue
            where = {k: r for r, k in enumerate(_identity_keys(stored))}
            rows = np.array([where.get(k, -1) for k in wanted], dtype=np.int64)
            covered = int(np.count_nonzero(rows >= 0))
            if covered:
                found.append((covered, other, rows))
        found.sort(key=lambda item: -item[0])
        return [(other, rows) for _, other, rows in found]

    def _load_verified(self, path: Path, key: CacheKey,
                       expect: dict[str, Any] | None = None) -> dict[str, np.ndarray] | None:
        if not path.is_file():
            return None
        try:
            arrays, meta = read_arrays(path)
            if meta.get("digest") != key.digest():
                raise ValueError("written for a different key")
            for name, value in (expect or {}).items():
                if meta.get(name) != value:
                    raise ValueError(f"holds rows {meta.get('start')}-{meta.get('stop')}, "
                                     f"not the {expect.get('start')}-{expect.get('stop')} "
                                     f"its name says")
        except PermissionError:
            self._unreadable.add(self.path(key))
            warn(path, "cache file is not readable (permission denied); leaving it in place "
                       "and computing without caching")
            return None
        except ValueError as err:
            warn(path, f"corrupt cache file ({err}); deleting it and recomputing")
            path.unlink(missing_ok=True)
            return None
        return arrays


def _flat_values(name: str) -> bool:
    """Flat arrays of variable-size features (see descriptors/features.py) are not
    one row per scan; every other stored array is."""
    return name.startswith("ragged:") and name.endswith(":values")
