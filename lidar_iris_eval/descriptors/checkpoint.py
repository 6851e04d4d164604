"""Reading a PyTorch checkpoint (``.pth`` / ``.pth.tar``) without PyTorch.

Shared by the learned methods (OverlapTransformer, BEVPlace++): nothing here
knows a network; each method checks the names and shapes it reads.

Both formats of ``torch.save`` are read: the zip archive (PyTorch >= 1.6, below)
and the older legacy stream (:func:`_read_legacy`).

Since PyTorch 1.6, ``torch.save`` writes a zip archive: ``<root>/data.pkl`` (a
pickle of the saved object), ``<root>/data/<key>`` (the raw bytes of each
tensor storage) and small text records (``version``, ``byteorder``). In the
pickle a tensor is a call ``torch._utils._rebuild_tensor_v2(storage, offset,
size, stride, requires_grad, hooks[, metadata])`` whose ``storage`` is a
*persistent id* ``("storage", <storage class>, key, location, numel)``.

A pickle can name and call any importable function, so loading one from an
unknown source can run arbitrary code. This reader never imports what a
pickle names: :class:`_RestrictedUnpickler` answers a fixed list of names with
its own stand-ins (tensors become NumPy arrays, ``OrderedDict`` a dict) and
refuses every other name, so a checkpoint that holds anything but tensors,
numbers, strings and plain containers is rejected before anything runs.
"""

from __future__ import annotations

import hashlib
import io
import pickle
import zipfile
from collections import OrderedDict
from pathlib import Path

import numpy as np

#: storage class name -> NumPy dtype of its elements ("bfloat16" handled apart)
_STORAGES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
    "BFloat16Storage": "bfloat16", "LongStorage": np.int64, "IntStorage": np.int32,
    "ShortStorage": np.int16, "CharStorage": np.int8, "ByteStorage": np.uint8,
    "BoolStorage": np.bool_,
}


class CheckpointError(ValueError):
    """The file is not a checkpoint this reader accepts (the message says why)."""


class _StorageType:
    def __init__(self, name: str):
        self.name = name


class _Storage:
    """One storage of the checkpoint; its bytes come from ``read`` (called on first use)."""

    def __init__(self, read, key: str, kind: _StorageType, numel: int, big_endian: bool):
        self.read, self.key, self.kind = read, key, kind
        self.numel, self.big_endian = int(numel), big_endian
        self._array = None

    def array(self) -> np.ndarray:
        if self._array is None:
            raw = self.read(self.key)
            dtype = _STORAGES[self.kind.name]
            order = ">" if self.big_endian else "<"
            if dtype == "bfloat16":  # the upper half of a float32
                half = np.frombuffer(raw, dtype=order + "u2").astype(np.uint32) << 16
                arr = half.view(np.float32)
            else:
                usable = len(raw) - len(raw) % np.dtype(dtype).itemsize
                arr = np.frombuffer(raw[:usable], dtype=np.dtype(dtype).newbyteorder(order))
            if arr.size < self.numel:
                raise CheckpointError(f"storage {self.key} holds {arr.size} elements, "
                                      f"the pickle says {self.numel} (truncated file?)")
            self._array = arr[: self.numel]
        return self._array


class _Pending:
    """A tensor record, turned into an array once every storage can be read."""

    def __init__(self, storage, offset, size, stride):
        self.storage, self.offset, self.size, self.stride = storage, offset, size, stride


def _rebuild_tensor(storage, offset, size, stride, *_rest) -> _Pending:
    """The record of ``torch._utils._rebuild_tensor_v2`` (read later by :func:`_tensor`)."""
    if not isinstance(storage, _Storage):
        raise CheckpointError("a tensor whose storage is not a storage of the archive")
    return _Pending(storage, offset, size, stride)


def _tensor(pending: _Pending) -> np.ndarray:
    """A NumPy copy of the tensor ``storage[offset:]`` viewed with ``size`` and ``stride``."""
    storage, offset, size, stride = pending.storage, pending.offset, pending.size, pending.stride
    if not isinstance(storage, _Storage):
        raise CheckpointError("a tensor whose storage is not a storage of the archive")
    flat = storage.array()
    size, stride, offset = tuple(int(s) for s in size), tuple(int(s) for s in stride), int(offset)
    if len(size) != len(stride) or any(s < 0 for s in size) or any(s < 0 for s in stride):
        raise CheckpointError(f"a tensor with size {size} and stride {stride}")
    if any(s == 0 for s in size):
        return np.zeros(size, dtype=flat.dtype)
    last = offset + sum((n - 1) * st for n, st in zip(size, stride, strict=True))
    if offset < 0 or last >= flat.size:
        raise CheckpointError(f"a tensor reaches element {last} of a storage of {flat.size}")
    view = np.lib.stride_tricks.as_strided(
        flat[offset:], shape=size, strides=tuple(st * flat.itemsize for st in stride),
        writeable=False)
    return np.array(view, dtype=flat.dtype.newbyteorder("="))


def _rebuild_parameter(data, *_rest) -> np.ndarray:
    return data


def _ordered_dict(*args) -> dict:
    return OrderedDict(*args)


#: (module, name) a checkpoint may name -> what this reader gives it instead
_ALLOWED = {
    ("collections", "OrderedDict"): _ordered_dict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_tensor"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
}


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, stream, read, big_endian: bool):
        super().__init__(stream)
        self.read, self.big_endian = read, big_endian
        self.storages: dict[str, _Storage] = {}

    def find_class(self, module: str, name: str):
        if (module, name) in _ALLOWED:
            return _ALLOWED[(module, name)]
        if module == "torch" and name in _STORAGES:
            return _StorageType(name)
        raise CheckpointError(f"it holds {module}.{name}, not only tensors and plain "
                              "containers; refused without running it")

    def persistent_load(self, pid):
        # zip: ("storage", type, key, location, numel); legacy adds a view record (None)
        if not (isinstance(pid, tuple) and len(pid) in (5, 6) and pid[0] == "storage"
                and isinstance(pid[1], _StorageType)):
            raise CheckpointError(f"an unknown persistent record {str(pid)[:60]!r}")
        if len(pid) == 6 and pid[5] is not None:
            raise CheckpointError("a storage view (legacy format); re-save with a current torch")
        kind, key, numel = pid[1], str(pid[2]), pid[4]
        if key not in self.storages:
            self.storages[key] = _Storage(self.read, key, kind, numel, self.big_endian)
        return self.storages[key]


#: the first pickle of a legacy (pre-1.6, non-zip) torch.save file
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C


def _read_legacy(data: bytes) -> object:
    """A legacy ``torch.save`` file: magic, protocol, system info, the object, the storage
    keys, then each storage as an int64 element count and its bytes, in key order."""
    stream = io.BytesIO(data)
    blobs: dict[str, bytes] = {}
    header = []
    for _ in range(3):
        header.append(_RestrictedUnpickler(stream, blobs.__getitem__, False).load())
    if header[0] != _LEGACY_MAGIC or not isinstance(header[2], dict):
        raise CheckpointError("not a file written by torch.save")
    big = not header[2].get("little_endian", True)
    unpickler = _RestrictedUnpickler(stream, blobs.__getitem__, big)
    obj = unpickler.load()
    keys = _RestrictedUnpickler(stream, blobs.__getitem__, False).load()
    if not isinstance(keys, list):
        raise CheckpointError("no storage list after the object")
    for key in keys:
        key = str(key)
        storage = unpickler.storages.get(key)
        if storage is None:
            raise CheckpointError(f"storage {key} is listed but never used")
        count = stream.read(8)
        if len(count) < 8:
            raise CheckpointError(f"storage {key} is missing (truncated file?)")
        n = int.from_bytes(count, "big" if big else "little", signed=True)
        size = n * (2 if storage.kind.name == "BFloat16Storage"
                    else np.dtype(_STORAGES[storage.kind.name]).itemsize)
        blobs[key] = stream.read(size)
        if len(blobs[key]) < size:
            raise CheckpointError(f"storage {key} is truncated")
    return _materialise(obj)


def read_checkpoint(path: str | Path) -> object:
    """The object a ``torch.save`` zip checkpoint holds, with tensors as NumPy arrays.

    Also reads the legacy (pre-1.6, non-zip) format. Raises :class:`CheckpointError`
    for anything else (a truncated file, a pickle naming functions or classes beyond tensors
    and ``OrderedDict``) and :class:`OSError` when the file cannot be read.
    """
    return checkpoint_from_bytes(Path(path).read_bytes())


def checkpoint_from_bytes(data: bytes) -> object:
    """:func:`read_checkpoint` of a file's bytes already in memory."""
    try:
        if data[:1] == b"\x80":  # a bare pickle: the legacy format
            return _read_legacy(data)
        if data[:2] != b"PK":
            raise CheckpointError("not a zip archive written by torch.save")
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            pickles = [n for n in archive.namelist() if n.endswith("/data.pkl")
                       and n.count("/") == 1]
            if len(pickles) != 1:
                raise CheckpointError("no <name>/data.pkl record: not a torch checkpoint")
            root = pickles[0].split("/")[0]
            names = set(archive.namelist())
            big = (f"{root}/byteorder" in names
                   and archive.read(f"{root}/byteorder").strip() == b"big")

            def read(key: str) -> bytes:
                try:
                    return archive.read(f"{root}/data/{key}")
                except KeyError:
                    raise CheckpointError(f"the archive has no storage {root}/data/{key}") \
                        from None

            unpickler = _RestrictedUnpickler(io.BytesIO(archive.read(pickles[0])), read, big)
            return _materialise(unpickler.load())  # reads the storages while open
    except CheckpointError:
        raise
    except (zipfile.BadZipFile, EOFError, pickle.UnpicklingError, ValueError, TypeError,
            AttributeError, IndexError, KeyError, OverflowError) as err:
        raise CheckpointError(f"unreadable checkpoint ({type(err).__name__}: "
                              f"{str(err)[:80]})") from None


def _materialise(obj):
    """Plain containers all the way down (no archive references left)."""
    if isinstance(obj, _Pending):
        return _tensor(obj)
    if isinstance(obj, dict):
        return {k: _materialise(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return type(obj)(_materialise(v) for v in obj)
    return obj


def state_dict(obj) -> dict[str, np.ndarray]:
    """The model weights in a checkpoint object: its ``state_dict`` entry (or itself),
    with a ``module.`` prefix (``nn.DataParallel``) removed."""
    if isinstance(obj, dict) and isinstance(obj.get("state_dict"), dict):
        obj = obj["state_dict"]
    if not isinstance(obj, dict):
        raise CheckpointError("no state_dict in the checkpoint")
    out = {}
    for key, value in obj.items():
        if isinstance(key, str) and isinstance(value, np.ndarray):
            out[key[len("module."):] if key.startswith("module.") else key] = value
    if not out:
        raise CheckpointError("the checkpoint holds no named tensors")
    return out


def read_weights_file(path: str | Path) -> tuple[dict[str, np.ndarray], str]:
    """The named arrays of a weights file and the SHA-256 of its bytes.

    ``.npz`` files are read with ``allow_pickle=False``; anything else as a
    ``torch.save`` checkpoint (:func:`read_checkpoint`, then :func:`state_dict`).
    The digest is of the file's bytes (what a cache key must follow: a file
    re-saved with other bytes is another input, even with the same arrays).

    Raises
    ------
    OSError
        The file cannot be read.
    CheckpointError
        The file is not weights this reader accepts (the message says why).
    """
    path = Path(path)
    data = path.read_bytes()
    digest = hashlib.sha256(data).hexdigest()
    if path.suffix == ".npz":
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as z:
                return {k: z[k] for k in z.files}, digest
        except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
            raise CheckpointError(f"unreadable weights ({err})") from None
    return state_dict(checkpoint_from_bytes(data)), digest
