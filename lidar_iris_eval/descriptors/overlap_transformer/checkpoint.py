"""Reading a PyTorch checkpoint (``.pth`` / ``.pth.tar``) without PyTorch.

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
    """One storage of the archive, read on first use."""

    def __init__(self, archive: zipfile.ZipFile, root: str, key: str, kind: _StorageType,
                 numel: int, big_endian: bool):
        self.archive, self.root, self.key, self.kind = archive, root, key, kind
        self.numel, self.big_endian = int(numel), big_endian
        self._array = None

    def array(self) -> np.ndarray:
        if self._array is None:
            name = f"{self.root}/data/{self.key}"
            try:
                raw = self.archive.read(name)
            except KeyError:
                raise CheckpointError(f"the archive has no storage {name}") from None
            dtype = _STORAGES[self.kind.name]
            order = ">" if self.big_endian else "<"
            if dtype == "bfloat16":  # the upper half of a float32
                half = np.frombuffer(raw, dtype=order + "u2").astype(np.uint32) << 16
                arr = half.view(np.float32)
            else:
                arr = np.frombuffer(raw, dtype=np.dtype(dtype).newbyteorder(order))
            if arr.size < self.numel:
                raise CheckpointError(f"storage {self.key} holds {arr.size} elements, "
                                      f"the pickle says {self.numel} (truncated file?)")
            self._array = arr[: self.numel]
        return self._array


def _rebuild_tensor(storage, offset, size, stride, *_rest) -> np.ndarray:
    """A NumPy copy of the tensor ``storage[offset:]`` viewed with ``size`` and ``stride``."""
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
    def __init__(self, data: bytes, archive: zipfile.ZipFile, root: str, big_endian: bool):
        super().__init__(io.BytesIO(data))
        self.archive, self.root, self.big_endian = archive, root, big_endian
        self.storages: dict[str, _Storage] = {}

    def find_class(self, module: str, name: str):
        if (module, name) in _ALLOWED:
            return _ALLOWED[(module, name)]
        if module == "torch" and name in _STORAGES:
            return _StorageType(name)
        raise CheckpointError(f"it holds {module}.{name}, not only tensors and plain "
                              "containers; refused without running it")

    def persistent_load(self, pid):
        if not (isinstance(pid, tuple) and len(pid) == 5 and pid[0] == "storage"
                and isinstance(pid[1], _StorageType)):
            raise CheckpointError(f"an unknown persistent record {str(pid)[:60]!r}")
        _, kind, key, _location, numel = pid
        key = str(key)
        if key not in self.storages:
            self.storages[key] = _Storage(self.archive, self.root, key, kind, numel,
                                          self.big_endian)
        return self.storages[key]


def read_checkpoint(path: str | Path) -> object:
    """The object a ``torch.save`` zip checkpoint holds, with tensors as NumPy arrays.

    Raises :class:`CheckpointError` for anything else (a legacy pre-1.6 file,
    a truncated archive, a pickle naming functions or classes beyond tensors
    and ``OrderedDict``) and :class:`OSError` when the file cannot be read.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(4)
    if head[:2] != b"PK":
        what = ("a legacy (pre-1.6) torch file; re-save it with a current torch, "
                "torch.save(torch.load(f), f)") if head[:1] == b"\x80" else \
            "not a zip archive written by torch.save"
        raise CheckpointError(what)
    try:
        with zipfile.ZipFile(path) as archive:
            pickles = [n for n in archive.namelist() if n.endswith("/data.pkl")
                       and n.count("/") == 1]
            if len(pickles) != 1:
                raise CheckpointError("no <name>/data.pkl record: not a torch checkpoint")
            root = pickles[0].split("/")[0]
            names = set(archive.namelist())
            big = (f"{root}/byteorder" in names
                   and archive.read(f"{root}/byteorder").strip() == b"big")
            unpickler = _RestrictedUnpickler(archive.read(pickles[0]), archive, root, big)
            obj = unpickler.load()
            for storage in unpickler.storages.values():  # read while the archive is open
                storage.array()
            return _materialise(obj)
    except CheckpointError:
        raise
    except (zipfile.BadZipFile, EOFError, pickle.UnpicklingError, ValueError, TypeError,
            AttributeError, IndexError, KeyError) as err:
        raise CheckpointError(f"unreadable checkpoint ({type(err).__name__}: "
                              f"{str(err)[:80]})") from None


def _materialise(obj):
    """Plain containers all the way down (no archive references left)."""
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
