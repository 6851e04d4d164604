"""Segment data sets from simulated worlds, for training ESM and for its own metrics.

Every scan of a simulated sequence is segmented exactly as at run time
(ground removed by its labels) and each segment is tagged with the physical
object most of its points hit (the simulator's per-point object ids), that
object's coarse class, the frame and the segment's centroid in the world.

Two segments are a **true pair** ("the same physical object seen from two
poses") when they carry the same object id, both are at least ``purity`` pure,
their world centroids lie within ``pair_radius`` metres (a long facade split
into pieces gives several segments per scan; only the same piece counts) and
their frames are at least ``min_frame_gap`` apart (neighbouring scans would be
near-duplicates). Negatives for training are other objects of the same class.

:func:`simulate_local_map_segments` does the same on **local maps** built as at
run time (:mod:`lidar_iris_eval.localmaps`: the scans of the last ``window``
frames, the input filter, gt poses, 0.1 m voxels, 50 m cylinder) and segmented
by the run-time segmenter (:func:`.local_segments.local_map_clusters`); a
segment's object is the one most of the filtered scan points inside its voxels
hit (the window's scans, each point tagged by the simulator). Its true pairs
use ``min_frame_gap = window`` (E): two local maps that far apart share no scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from lidar_iris_eval.descriptors.esm.segmentation import SegmentParams, segment_scan

#: SemanticKITTI class -> coarse class used for within-class negatives
COARSE = {10: 1, 252: 1, 50: 2, 70: 3, 71: 3, 80: 4, 81: 4, 51: 5}
COARSE_NAMES = {0: "other", 1: "car", 2: "building", 3: "vegetation", 4: "pole", 5: "fence"}


@dataclass
class SegmentSet:
    """Raw segments (voxel points in the sensor frame) with their tags.

    ``points[offsets[s]:offsets[s + 1]]`` are segment ``s``'s voxel points.
    """

    points: np.ndarray  # (P, 3) float32
    offsets: np.ndarray  # (S + 1,) int64
    object_id: np.ndarray  # (S,) int64 (0: no dominant object)
    coarse: np.ndarray  # (S,) int8
    frame: np.ndarray  # (S,) int64
    world: np.ndarray  # (S, 3) centroid in the world frame
    purity: np.ndarray  # (S,) fraction of points on the dominant object
    world_id: np.ndarray  # (S,) which simulated world (seed index)

    def __len__(self) -> int:
        return len(self.frame)

    def segment(self, s: int) -> np.ndarray:
        return self.points[self.offsets[s]:self.offsets[s + 1]]

    def save(self, path) -> None:
        """Write atomically (temporary file, then :func:`os.replace`)."""
        import os
        from pathlib import Path

        path = Path(path)
        tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}.npz")
        np.savez_compressed(tmp, **{k: getattr(self, k) for k in self.__dataclass_fields__})
        os.replace(tmp, path)

    @classmethod
    def load(cls, path) -> SegmentSet:
        with np.load(path) as z:
            return cls(**{k: z[k] for k in cls.__dataclass_fields__})

    @staticmethod
    def concat(parts: list[SegmentSet]) -> SegmentSet:
        offs, base = [np.zeros(1, np.int64)], 0
        for p in parts:
            offs.append(p.offsets[1:] + base)
            base += int(p.offsets[-1])
        out = {k: np.concatenate([getattr(p, k) for p in parts])
               for k in SegmentSet.__dataclass_fields__ if k != "offsets"}
        return SegmentSet(offsets=np.concatenate(offs), **out)


def simulate_segments(
    config_overrides: dict, world_index: int = 0, params: SegmentParams | None = None,
    every: int = 1, progress: bool = True, shape_variety: bool = False,
) -> SegmentSet:
    """Simulate a sequence in memory and segment every ``every``-th scan.

    ``shape_variety`` builds the world with :attr:`WorldParams.shape_variety`
    (varied car bodies and tree crowns; never used by written sequences).
    """
    from lidar_iris_eval.simulate.pipeline import _NOISE, build_scenario
    from lidar_iris_eval.simulate.presets import resolve_config
    from lidar_iris_eval.simulate.sensors import simulate_scan
    from lidar_iris_eval.simulate.world import WorldParams

    cfg = resolve_config(None, config_overrides)
    scen = build_scenario(cfg, WorldParams(shape_variety=shape_variety))
    dirs = scen.sensor.grid.directions
    pts, offs, obj, coarse, frame, world, purity = [], [0], [], [], [], [], []
    frames = range(0, len(scen.poses), every)
    for i in tqdm(frames, desc=f"segments world {world_index}", disable=not progress,
                  leave=False):
        rng = np.random.default_rng([cfg.seed, _NOISE, i])
        scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(i), scen.poses[i],
                             rng, dirs)
        ids = scen.object_ids(i, scan.row)
        segs = segment_scan(scan.points, scan.label, params)
        pose = scen.poses[i]
        for s in range(len(segs)):
            m = segs.members[s]
            vals, counts = np.unique(ids[m], return_counts=True)
            top = int(np.argmax(counts))
            dominant = int(vals[top])
            cls_vals, cls_counts = np.unique(scan.label[m][ids[m] == dominant] & 0xFFFF,
                                             return_counts=True)
            cls = int(cls_vals[np.argmax(cls_counts)])
            raw = _voxel_points(scan.points[m], params)
            pts.append(raw.astype(np.float32))
            offs.append(offs[-1] + len(raw))
            obj.append(dominant)
            coarse.append(COARSE.get(cls, 0))
            frame.append(i)
            world.append(pose[:3, :3] @ segs.centroids[s] + pose[:3, 3])
            purity.append(counts[top] / counts.sum())
    n = len(frame)
    return SegmentSet(
        points=np.concatenate(pts) if pts else np.zeros((0, 3), np.float32),
        offsets=np.asarray(offs, np.int64), object_id=np.asarray(obj, np.int64),
        coarse=np.asarray(coarse, np.int8), frame=np.asarray(frame, np.int64),
        world=np.asarray(world).reshape(n, 3), purity=np.asarray(purity),
        world_id=np.full(n, world_index, np.int64),
    )


def _voxel_points(points: np.ndarray, params: SegmentParams | None) -> np.ndarray:
    from lidar_iris_eval.descriptors.esm.segmentation import voxelise

    p = params or SegmentParams()
    vox, _ = voxelise(np.asarray(points, np.float64), p.voxel)
    return vox


def true_pairs(
    data: SegmentSet, pair_radius: float = 2.0, min_frame_gap: int = 10, purity: float = 0.8
) -> np.ndarray:
    """(n, 2) index pairs (a < b) of segments showing the same piece of the same object."""
    from scipy.spatial import cKDTree

    ok = (data.object_id > 0) & (data.purity >= purity)
    idx = np.nonzero(ok)[0]
    key = data.world[idx] + 1e4 * data.world_id[idx, None]
    pairs = cKDTree(key).query_pairs(pair_radius, output_type="ndarray")
    a, b = idx[pairs[:, 0]], idx[pairs[:, 1]]
    same = (data.object_id[a] == data.object_id[b]) & (data.world_id[a] == data.world_id[b])
    same &= np.abs(data.frame[a] - data.frame[b]) >= min_frame_gap
    out = np.stack([a[same], b[same]], axis=1)
    return np.sort(out, axis=1)


def simulate_local_map_segments(
    config_overrides: dict, world_index: int = 0, params: SegmentParams | None = None,
    every: int = 10, window: int = 30, input_filter: str = "all", map_radius: float = 50.0,
    max_points: int = 1024, progress: bool = True, shape_variety: bool = False,
) -> SegmentSet:
    """Simulate a sequence in memory; segment the local map of every ``every``-th frame.

    Every scan is simulated (a local map holds the last ``window`` scans, placed
    by the gt poses after the named ``input_filter``). A segment's stored points
    are its voxel centroids in the world frame (as at run time), at most
    ``max_points`` of them (a seeded uniform subset: the network resamples 256
    uniformly anyway); ``world`` is the centroid of all its voxels.
    """
    from collections import deque

    from lidar_iris_eval.descriptors.esm.local_segments import local_map_clusters
    from lidar_iris_eval.localmaps import LocalMap
    from lidar_iris_eval.localmaps import input_filter as get_filter
    from lidar_iris_eval.localmaps.grid import encode
    from lidar_iris_eval.simulate.pipeline import _NOISE, build_scenario
    from lidar_iris_eval.simulate.presets import resolve_config
    from lidar_iris_eval.simulate.sensors import simulate_scan
    from lidar_iris_eval.simulate.world import WorldParams

    p = params or SegmentParams()
    cfg = resolve_config(None, config_overrides)
    scen = build_scenario(cfg, WorldParams(shape_variety=shape_variety))
    dirs = scen.sensor.grid.directions
    filt = get_filter(input_filter)
    lm = LocalMap(window, p.voxel, map_radius, filt)
    voxel_mm = lm.grid.voxel_mm
    recent: deque = deque()  # (frame, voxel keys, object ids, classes) of the window's points
    pts, offs, obj, coarse, frame, world, purity = [], [0], [], [], [], [], []
    for i in tqdm(range(len(scen.poses)), desc=f"local maps world {world_index}",
                  disable=not progress, leave=False):
        rng = np.random.default_rng([cfg.seed, _NOISE, i])
        pose = scen.poses[i]
        scan = simulate_scan(scen.sensor, scen.world.ground, scen.primitives(i), pose, rng, dirs)
        keep = filt.mask(scan.points)
        placed = np.asarray(scan.points, np.float64)[keep, :3] @ pose[:3, :3].T + pose[:3, 3]
        keys = encode(np.floor_divide(np.rint(placed * 1000.0).astype(np.int64), voxel_mm))
        recent.append((i, keys, scen.object_ids(i, scan.row)[keep],
                       (scan.label[keep] & 0xFFFF).astype(np.int64)))
        while recent[0][0] <= i - window:
            recent.popleft()
        lm.update(i, scan.points, pose)
        if i % every:
            continue
        centroids = lm.grid.centroids()
        clusters = local_map_clusters(centroids, p)
        if not clusters:
            continue
        seg_of = -np.ones(len(centroids), np.int64)
        for s, members in enumerate(clusters):
            seg_of[members] = s
        wkeys = np.concatenate([r[1] for r in recent])
        wids = np.concatenate([r[2] for r in recent])
        wcls = np.concatenate([r[3] for r in recent])
        pos = np.minimum(np.searchsorted(lm.grid.keys, wkeys), len(centroids) - 1)
        hit = lm.grid.keys[pos] == wkeys
        seg = np.where(hit, seg_of[pos], -1)
        inside = seg >= 0
        tags = _dominant(seg[inside], wids[inside], wcls[inside], len(clusters))
        sub = np.random.default_rng([cfg.seed, i])
        for s, members in enumerate(clusters):
            vox = centroids[members]
            dominant, share, cls = tags[s]
            kept = vox if len(vox) <= max_points else \
                vox[np.sort(sub.choice(len(vox), max_points, replace=False))]
            pts.append(kept.astype(np.float32))
            offs.append(offs[-1] + len(kept))
            obj.append(dominant)
            coarse.append(COARSE.get(cls, 0))
            frame.append(i)
            world.append(vox.mean(axis=0))
            purity.append(share)
    n = len(frame)
    return SegmentSet(
        points=np.concatenate(pts) if pts else np.zeros((0, 3), np.float32),
        offsets=np.asarray(offs, np.int64), object_id=np.asarray(obj, np.int64),
        coarse=np.asarray(coarse, np.int8), frame=np.asarray(frame, np.int64),
        world=np.asarray(world).reshape(n, 3), purity=np.asarray(purity, np.float64),
        world_id=np.full(n, world_index, np.int64),
    )


def _dominant(seg: np.ndarray, ids: np.ndarray, cls: np.ndarray, n: int) -> list:
    """Per segment ``0..n-1``: (dominant object id, its share of the points, its class).

    ``seg``, ``ids``, ``cls``: a segment, object id and class per point. The
    class is the most frequent one among the dominant object's points; a
    segment without points gets ``(0, 0.0, 0)``.
    """
    out = [(0, 0.0, 0)] * n
    if len(seg) == 0:
        return out
    pairs, counts = np.unique(np.stack([seg, ids]), axis=1, return_counts=True)
    totals = np.bincount(seg, minlength=n)
    for s in np.unique(pairs[0]):
        cols = np.nonzero(pairs[0] == s)[0]
        top = cols[np.argmax(counts[cols])]  # ties: the smaller id (np.unique's order)
        dominant = int(pairs[1, top])
        m = (seg == s) & (ids == dominant)
        vals, c = np.unique(cls[m], return_counts=True)
        out[int(s)] = (dominant, float(counts[top] / totals[s]), int(vals[np.argmax(c)]))
    return out


def negative_candidates(coarse: np.ndarray, objects: np.ndarray, anchors_world=None,
                        positives_world=None, worlds=None, min_distance: float = 0.0,
                        ) -> np.ndarray:
    """``(B, B)`` True where pair ``j``'s positive may be anchor ``i``'s negative.

    The in-batch rule of training: another object of the same coarse class, or
    any other object when the batch holds no other object of that class. With
    ``min_distance > 0`` (plain sequences, whose objects are centroid tracks),
    a positive whose world centroid (``positives_world``) lies closer than
    ``min_distance`` m to the anchor's (``anchors_world``) in the same world
    (``worlds``) is never a negative: it may be the same thing, segmented
    differently.
    """
    coarse, objects = np.asarray(coarse), np.asarray(objects)
    other = objects[:, None] != objects[None, :]
    if min_distance > 0 and anchors_world is not None:
        a, p = np.asarray(anchors_world, float), np.asarray(positives_world, float)
        far = np.linalg.norm(a[:, None, :] - p[None, :, :], axis=2) >= min_distance
        if worlds is not None:
            w = np.asarray(worlds)
            far |= w[:, None] != w[None, :]
        other &= far
    same_cls = (coarse[:, None] == coarse[None, :]) & other
    return np.where(same_cls.any(axis=1, keepdims=True), same_cls, other)


#: positives of a plain sequence: two views whose world centroids lie this close (m)
#: (the segmentation report's ``--match``: the same segment, re-segmented in another map)
SEQUENCE_MATCH = 1.0


def sequence_local_map_segments(
    seq, esm, every: int = 10, match: float = SEQUENCE_MATCH, max_points: int = 1024,
    limit: int | None = None, world_index: int = 0, progress=None,
) -> SegmentSet:
    """The local-map segments of any sequence with poses, tagged by world centroids.

    Every frame's local map is built exactly as ``liris eval -d esm`` builds it
    (``esm``: a local-map ESM descriptor bound to its window, e.g.
    ``get_descriptor("esm", "local-maps").bind_exclusion(30)``; its input filter,
    voxels, crop and the sequence's poses) and every ``every``-th one is
    segmented by the descriptor's front end (:func:`.local_segments.local_map_clusters`
    with ``esm.segment_params``). No object ids exist, so a segment's
    ``object_id`` is its **track**: the connected component of the graph that
    links two segments (of any two maps) whose world centroids lie within
    ``match`` m (1 m), numbered from 1. :func:`true_pairs` with
    ``pair_radius = match`` and ``min_frame_gap = W`` then gives exactly the
    pairs of views within ``match`` m in maps that share no scan. ``coarse`` is
    0 (no classes) and ``purity`` 1. Stored points are world-frame voxel
    centroids (at most ``max_points``, a seeded subset), as
    :func:`simulate_local_map_segments` stores them.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from lidar_iris_eval.descriptors.esm.local_segments import local_map_clusters
    from lidar_iris_eval.localmaps import local_maps

    poses = getattr(seq, "poses", None)
    if poses is None:
        from lidar_iris_eval.errors import LirisError

        raise LirisError(getattr(seq, "path", None), "has no poses; training needs them "
                                                     "(give --poses)")
    poses = np.asarray(poses, dtype=np.float64)
    n = len(seq) if limit is None else min(int(limit), len(seq))
    sp = esm.segment_params
    pts, offs, frame, world = [], [0], [], []
    for fr, _ in local_maps(lambda j: np.asarray(seq[j])[:, :3], poses,
                            esm.local_map_settings(), 0, n):
        i = int(fr.frame)
        if progress is not None:
            progress(i + 1, n)
        if i % every:
            continue
        centroids = np.asarray(fr.points, dtype=np.float64)
        sub = np.random.default_rng([int(sp.seed), i])
        for members in local_map_clusters(centroids, sp):
            vox = centroids[members]
            kept = vox if len(vox) <= max_points else \
                vox[np.sort(sub.choice(len(vox), max_points, replace=False))]
            pts.append(kept.astype(np.float32))
            offs.append(offs[-1] + len(kept))
            frame.append(i)
            world.append(vox.mean(axis=0))
    s = len(frame)
    world_arr = np.asarray(world, dtype=np.float64).reshape(s, 3)
    if s:
        pairs = cKDTree(world_arr).query_pairs(match, output_type="ndarray")
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(s, s))
        _, track = connected_components(graph, directed=False)
    else:
        track = np.zeros(0, np.int64)
    return SegmentSet(
        points=np.concatenate(pts) if pts else np.zeros((0, 3), np.float32),
        offsets=np.asarray(offs, np.int64), object_id=np.asarray(track, np.int64) + 1,
        coarse=np.zeros(s, np.int8), frame=np.asarray(frame, np.int64), world=world_arr,
        purity=np.ones(s), world_id=np.full(s, world_index, np.int64),
    )


def relabel_worlds(parts: list[SegmentSet]) -> SegmentSet:
    """Concatenate segment sets, part ``k`` becoming world ``k`` (pairs never cross parts)."""
    return SegmentSet.concat([SegmentSet(**{**{f: getattr(p, f) for f in p.__dataclass_fields__},
                                            "world_id": np.full(len(p), k, np.int64)})
                              for k, p in enumerate(parts)])
