"""Variable-size per-scan features ("feature sets") stored as flat arrays plus offsets.

A segment or object method describes a scan by a *feature set*: a dict of
arrays, some of which differ in their first dimension between scans (K
objects, K segments), e.g.::

    {"graph": (366,) float64, "centroids": (K, 3) float64, "classes": (K,) int8}

``np.stack`` cannot hold that, so :class:`RaggedFeatures` keeps, per key, one
flat array of every scan's rows concatenated and the offsets where each scan
starts. That layout is what the cache stores (``ragged:<key>:values`` and
``ragged:<key>:counts``), chunk by chunk, so extraction of variable-size
features is cached and resumable like any fixed-size descriptor.

Rules: every scan returns the same keys; for each key the trailing
dimensions and the dtype are the same for every scan; only the first
dimension may vary. Scalars (0-d arrays) are not allowed — return shape (1,).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

_PREFIX = "ragged:"


@dataclass(frozen=True)
class RaggedFeatures:
    """Feature sets of ``n`` scans: per key, flat ``values`` and ``offsets (n + 1,)``.

    ``features[i]`` is the dict of scan ``i`` (views into the flat arrays);
    ``features[a:b]`` a :class:`RaggedFeatures` of those scans.
    """

    values: Mapping[str, np.ndarray]
    offsets: Mapping[str, np.ndarray]

    def __post_init__(self) -> None:
        if set(self.values) != set(self.offsets):
            raise ValueError("values and offsets must have the same keys")
        lengths = {len(o) for o in self.offsets.values()}
        if len(lengths) > 1:
            raise ValueError(f"keys disagree on the number of scans: {sorted(lengths)}")
        for key, off in self.offsets.items():
            if len(off) == 0 or off[0] != 0 or off[-1] != len(self.values[key]):
                raise ValueError(f"offsets of {key!r} do not cover its values")

    # ------------------------------------------------------------------ building

    @classmethod
    def from_list(cls, items: Sequence[Mapping[str, np.ndarray]], source: str = "compute"
                  ) -> RaggedFeatures:
        """Pack per-scan feature dicts; a key, dtype or trailing-shape change is an error."""
        if not items:
            raise ValueError("no feature sets to pack")
        keys = list(items[0])
        first = {k: np.asarray(items[0][k]) for k in keys}
        for k, a in first.items():
            if ":" in k:
                raise ValueError(f"{source}: feature key {k!r} may not contain ':'")
            if a.ndim == 0:
                raise ValueError(f"{source}: feature {k!r} is a scalar; return shape (1,)")
        arrays: dict[str, list[np.ndarray]] = {k: [] for k in keys}
        for i, item in enumerate(items):
            if list(item) != keys:
                raise ValueError(f"{source}: scan {i} has keys {list(item)}, expected {keys}")
            for k in keys:
                a = np.asarray(item[k])
                if a.dtype != first[k].dtype or a.shape[1:] != first[k].shape[1:]:
                    raise ValueError(
                        f"{source}: feature {k!r} of scan {i} is {a.dtype}{a.shape}; every scan "
                        f"must give {first[k].dtype} with trailing shape {first[k].shape[1:]}"
                    )
                arrays[k].append(a)
        values = {k: np.concatenate(v) for k, v in arrays.items()}
        offsets = {k: _offsets([len(a) for a in v]) for k, v in arrays.items()}
        return cls(values, offsets)

    @classmethod
    def concatenate(cls, parts: Sequence[RaggedFeatures]) -> RaggedFeatures:
        """Scans of ``parts`` one after another (chunks of one extraction)."""
        keys = list(parts[0].values)
        for p in parts[1:]:
            if list(p.values) != keys:
                raise ValueError(f"feature keys differ between chunks: {keys} vs {list(p.values)}")
            for k in keys:
                a, b = parts[0].values[k], p.values[k]
                if a.dtype != b.dtype or a.shape[1:] != b.shape[1:]:
                    raise ValueError(f"feature {k!r} differs between chunks: "
                                     f"{a.dtype}{a.shape[1:]} vs {b.dtype}{b.shape[1:]}")
        values = {k: np.concatenate([p.values[k] for p in parts]) for k in keys}
        offsets = {k: _offsets(np.concatenate([p.counts(k) for p in parts])) for k in keys}
        return cls(values, offsets)

    # ------------------------------------------------------------------ cache form

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat arrays for the cache: ``ragged:<key>:values`` and ``ragged:<key>:counts``."""
        out = {}
        for k in self.values:
            out[f"{_PREFIX}{k}:values"] = np.ascontiguousarray(self.values[k])
            out[f"{_PREFIX}{k}:counts"] = self.counts(k)
        return out

    @staticmethod
    def in_arrays(arrays: Mapping[str, np.ndarray]) -> bool:
        """True when a cache dict holds ragged features."""
        return any(name.startswith(_PREFIX) for name in arrays)

    @staticmethod
    def is_flat_values(name: str) -> bool:
        """True for cache array names whose length is not the number of scans."""
        return name.startswith(_PREFIX) and name.endswith(":values")

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, np.ndarray]) -> RaggedFeatures:
        """Inverse of :meth:`to_arrays` (other names in ``arrays`` are ignored)."""
        values, offsets = {}, {}
        for name, arr in arrays.items():
            if name.startswith(_PREFIX) and name.endswith(":counts"):
                k = name[len(_PREFIX): -len(":counts")]
                values[k] = arrays[f"{_PREFIX}{k}:values"]
                offsets[k] = _offsets(arr)
        return cls(values, offsets)

    @staticmethod
    def n_scans_in(arrays: Mapping[str, np.ndarray]) -> int:
        """Number of scans recorded in a cache dict of ragged features."""
        for name, arr in arrays.items():
            if name.startswith(_PREFIX) and name.endswith(":counts"):
                return len(arr)
        return 0

    # ------------------------------------------------------------------ access

    @property
    def keys(self) -> list[str]:
        return list(self.values)

    def __len__(self) -> int:
        return len(next(iter(self.offsets.values()))) - 1 if self.offsets else 0

    def counts(self, key: str) -> np.ndarray:
        """``(n,)`` int64 first-dimension size of ``key`` in each scan."""
        return np.diff(self.offsets[key]).astype(np.int64)

    def __getitem__(self, index):
        if isinstance(index, slice):
            a, b, step = index.indices(len(self))
            if step != 1:
                raise ValueError("only contiguous slices of features are supported")
            return self._range(a, max(a, b))
        if isinstance(index, (np.ndarray, list, tuple)):
            return self._take(np.asarray(index, dtype=np.int64).reshape(-1))
        i = int(index)
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"scan {index} out of range for {len(self)} scans")
        return {k: v[self.offsets[k][i]: self.offsets[k][i + 1]] for k, v in self.values.items()}

    def _range(self, a: int, b: int) -> RaggedFeatures:
        values, offsets = {}, {}
        for k, v in self.values.items():
            off = self.offsets[k]
            values[k] = v[off[a]: off[b]]
            offsets[k] = off[a: b + 1] - off[a]
        return RaggedFeatures(values, offsets)

    def _take(self, rows: np.ndarray) -> RaggedFeatures:
        """The scans ``rows`` (any order, negatives from the end) as a new, copied set; what
        the block pass reads for a non-contiguous run of queries."""
        n = len(self)
        rows = np.where(rows < 0, rows + n, rows)
        if len(rows) and (rows.min() < 0 or rows.max() >= n):
            raise IndexError(f"scans {rows.min()}..{rows.max()} out of range for {n} scans")
        values, offsets = {}, {}
        for k, v in self.values.items():
            off = self.offsets[k]
            parts = [v[off[i]: off[i + 1]] for i in rows]
            values[k] = np.concatenate(parts) if parts else v[:0]
            offsets[k] = _offsets([len(p) for p in parts])
        return RaggedFeatures(values, offsets)

    def stacked(self, key: str) -> np.ndarray:
        """``(n, c, ...)`` of a key with the same size ``c`` in every scan, squeezed to
        ``(n, c)`` for 1-D per-scan arrays — e.g. a fixed-length global vector."""
        counts = self.counts(key)
        if len(counts) and np.any(counts != counts[0]):
            raise ValueError(f"feature {key!r} varies in size between scans; it cannot be stacked")
        c = int(counts[0]) if len(counts) else 0
        v = self.values[key]
        return v.reshape(len(counts), c, *v.shape[1:])


def _offsets(counts) -> np.ndarray:
    out = np.zeros(len(counts) + 1, dtype=np.int64)
    np.cumsum(np.asarray(counts, dtype=np.int64), out=out[1:])
    return out
