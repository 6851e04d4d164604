"""Persistent segment ids and the embedding cache of the local-map mode.

SegMap segments its local map incrementally and keeps an id per segment
across scans (ethz-asl/segmap ``incremental_segmenter.hpp``: when two
segments merge, the older, smaller id survives and the merge is logged); its
CNN descriptor re-describes a segment only when it grew by at least 10 % since
it was last described (``cnn.cpp``, ``kMinChangeBeforeDescription = 0.1``).

Here the partition of every frame is the Euclidean clustering of the whole
local map (:func:`~.local_segments.local_map_clusters`, the same segments as
:func:`~.local_segments.segment_local_map`), and the ids are carried from the
previous frame by shared voxels (voxel keys,
:attr:`~lidar_iris_eval.localmaps.LocalMapFrame.keys`):

1. **heir**: each previous segment's id goes to the current segment that holds
   most of its voxels (ties: the earlier segment in key order). So when a
   segment **splits** (a scan leaving the window disconnects it), the piece
   holding most of its voxels keeps the id and the others are new;
2. **merge**: a current segment that is heir of several previous ids takes the
   smallest (SegMap's rule: the oldest survives); the others end and are
   logged in :attr:`SegmentTracker.merges` as ``(frame, old id, surviving id)``;
3. **new**: a segment heir of no id gets a new one, ``birth frame * 10,000 + k``
   for the ``k``-th new segment of that frame (so ids are unique in a sequence
   and say where a segment was first seen).

Only segments (100-15,000 voxels) carry ids; a cluster outside those sizes has
none (SegMap's ``kNoId``), so an id ends when its segment falls below 100
voxels. A cluster above 15,000 voxels is not invalidated for good as in
SegMap: it is simply no segment in that frame.

**Embedding cache** (``describe``):

* ``all``: every segment is described at every frame (the uncached baseline);
* ``exact``: a segment reuses its embedding when its content (voxel keys and
  centroids) is bit-identical to when it was described; the resampling seed
  comes from the content (:func:`~.local_segments.content_seed`), so a cached
  embedding equals a recomputed one;
* ``growth`` (SegMap's rule): a segment reuses the embedding of its id until
  it holds at least ``(1 + growth)`` times the voxels it had when last
  described (``growth`` = 0.1, SegMap's value). A segment that shrinks keeps
  its embedding, as in SegMap.

Centroids, sizes and ids are always of the current frame. Tracking state lives
in one extraction pass: :meth:`SegmentTracker.reset` starts it afresh (the
extraction calls it at the start of every chunk of frames), so ids and the
``growth`` cache depend on where a chunk starts (chunks are fixed, 50 frames,
so the same command gives the same features); ``all`` and ``exact`` give
features that do not.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

#: new ids are ``birth frame * ID_STRIDE + k``
ID_STRIDE = 10_000
DESCRIBE_RULES = ("all", "exact", "growth")


def content_digest(keys: np.ndarray, points: np.ndarray) -> bytes:
    """A digest of a segment's voxel keys and centroids (``exact`` rule)."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.ascontiguousarray(keys, dtype="<i8").tobytes())
    h.update(np.ascontiguousarray(points, dtype="<f8").tobytes())
    return h.digest()


@dataclass
class _Cached:
    size: int
    digest: bytes
    embedding: np.ndarray
    quality: float


@dataclass
class SegmentTracker:
    """Ids carried frame to frame (module docstring) and the embeddings of live ids."""

    describe: str = "growth"
    growth: float = 0.1
    frame: int = -1
    keys: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    cache: dict = field(default_factory=dict)
    merges: list = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.describe not in DESCRIBE_RULES:
            raise ValueError(f"describe must be one of {DESCRIBE_RULES}, got {self.describe!r}")

    def reset(self) -> None:
        """Forget every id and embedding (a new extraction pass)."""
        self.frame = -1
        self.keys = np.zeros(0, np.int64)
        self.ids = np.zeros(0, np.int64)
        self.cache = {}
        self.merges = []

    def assign(self, frame: int, segment_keys: list[np.ndarray]) -> np.ndarray:
        """Ids of the segments of ``frame`` (each given by its sorted voxel keys).

        A frame that does not follow the last one (``frame != last + 1``)
        starts tracking afresh.
        """
        if frame != self.frame + 1:
            self.reset()
        n = len(segment_keys)
        sizes = np.array([len(k) for k in segment_keys], np.int64)
        flat = np.concatenate(segment_keys) if n else np.zeros(0, np.int64)
        seg_of = np.repeat(np.arange(n), sizes)
        out = np.full(n, -1, np.int64)
        if len(self.keys) and len(flat):
            pos = np.searchsorted(self.keys, flat)
            pos = np.minimum(pos, len(self.keys) - 1)
            hit = self.keys[pos] == flat
            prev = self.ids[pos[hit]]
            if len(prev):
                # each (segment, previous id) pair packed into one int64 whose order is the
                # pairs' lexicographic order (ids are >= 0), counted by one 1-D np.unique
                base = int(prev.max()) + 1
                if n * base >= 2**62:  # pragma: no cover - ids past 4e18 / segments
                    raise RuntimeError("segment ids too large to pack")
                packed, shared = np.unique(seg_of[hit] * base + prev, return_counts=True)
                uniq = np.stack([packed // base, packed % base], 1)
                # heir of each previous id: most shared voxels, then the earlier segment
                order = np.lexsort((uniq[:, 0], -shared, uniq[:, 1]))
                uniq = uniq[order]
                first = np.ones(len(uniq), bool)
                first[1:] = uniq[1:, 1] != uniq[:-1, 1]
                heirs = uniq[first]  # (segment, previous id), one row per previous id
                for s in np.unique(heirs[:, 0]):
                    inherited = np.sort(heirs[heirs[:, 0] == s, 1])
                    out[s] = inherited[0]  # the oldest (smallest) id survives a merge
                    for old in inherited[1:]:
                        self.merges.append((int(frame), int(old), int(inherited[0])))
        new = np.nonzero(out < 0)[0]
        if len(new) >= ID_STRIDE:
            raise RuntimeError(f"more than {ID_STRIDE} new segments in one frame")
        out[new] = int(frame) * ID_STRIDE + np.arange(len(new))
        order = np.argsort(flat, kind="stable")
        self.keys, self.ids = flat[order], np.repeat(out, sizes)[order]
        self.frame = int(frame)
        return out

    def lookup(self, seg_id: int, size: int, digest: bytes) -> tuple[np.ndarray, float] | None:
        """The cached ``(embedding, quality)`` of ``seg_id`` if the rule allows reuse."""
        c = self.cache.get(int(seg_id))
        if c is None or self.describe == "all":
            return None
        if self.describe == "exact":
            return (c.embedding, c.quality) if c.digest == digest else None
        if size < (1.0 + self.growth) * c.size:
            return c.embedding, c.quality
        return None

    def store(self, seg_id: int, size: int, digest: bytes, embedding: np.ndarray,
              quality: float) -> None:
        """Remember the embedding ``seg_id`` was described with."""
        self.cache[int(seg_id)] = _Cached(int(size), digest, np.array(embedding), float(quality))

    def forget_ended(self, live_ids: np.ndarray) -> None:
        """Drop the cache of ids no longer alive."""
        live = set(int(i) for i in live_ids)
        for k in [k for k in self.cache if k not in live]:
            del self.cache[k]
