"""MapClosures' native mode: local maps split by distance, closures between maps.

This reproduces how MapClosures' own ``map_closure_pipeline`` (``pipeline.py``
of PRBonn/MapClosures 2.2.0) runs, with the sequence's poses (``gt``, the
default) or KISS-ICP configured as its pipeline does (``kiss-icp``: 1 m
voxels, 100 m range; no per-point times, so no deskewing), and scores it the
way its ``tools/evaluation.py`` does:

* **local maps**: every scan (points within ``max_range``) is integrated
  into a voxel map (``density_map_resolution`` m) in the frame of the map's
  first pose. When the current pose is more than ``map_range`` m from that
  first pose (a displacement, not the path length; its pipeline uses KISS-ICP's
  ``max_range`` 100 m), or at the last scan, the map is closed: it is given to
  ``get_closures(map_index, map)``, its points farther than ``max_range`` from
  the current pose are dropped and the rest carried into the next map, whose
  frame is the current pose;
* **predictions**: every closure the C++ returns (maps ``ref < query - 3``,
  more than 2 inliers), with its inliers;
* **ground truth of map pairs** (liris's, documented because 2.2.0 reads a
  ``local_map_gt_closures.txt`` it does not generate): maps ``a < b - 3``
  form a true closure when their 3-D occupancies overlap,
  ``|A ∩ B| / min(|A|, |B|) >= overlap`` (0.5) on ``overlap_voxel`` (0.5 m)
  voxels of their points placed with the ground-truth poses: the overlap
  measure and constants of MapClosures' former ``tools/gt_closures.py``
  (removed in 2.x), applied to whole local maps;
* **metrics**: for each inlier threshold ``t`` from 3 up, the predictions with
  at least ``t`` inliers against the ground-truth pairs (TP, FP, FN,
  precision, recall, F1), as its ``EvaluationPipeline.compute_metrics``; also
  F1max and the row at its pipeline's acceptance (``inliers >
  inliers_threshold``, i.e. ``t = inliers_threshold + 1``).

Run it with ``python -m lidar_iris_eval.descriptors.mapclosures.native SEQ``.
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from lidar_iris_eval.descriptors.mapclosures import backend
from lidar_iris_eval.descriptors.mapclosures.descriptor import MAPS_SKIPPED, MapClosuresParams


@dataclass(frozen=True)
class NativeSettings:
    """Native-mode settings; defaults are MapClosures' pipeline (``map_range`` =
    ``max_range`` = KISS-ICP's 100 m) and the former GT tool (0.5 overlap, 0.5 m)."""

    map_range: float = 100.0
    max_range: float = 100.0
    overlap: float = 0.5
    overlap_voxel: float = 0.5
    odometry: str = "gt"

    def __post_init__(self) -> None:
        if self.odometry not in ODOMETRY:
            from lidar_iris_eval.errors import LirisError

            raise LirisError("--odometry", f"{self.odometry!r}: choose from {', '.join(ODOMETRY)}")


#: where the native mode's scan poses come from: the sequence's, or KISS-ICP as MapClosures runs
ODOMETRY = ("gt", "kiss-icp")


@dataclass
class NativeMaps:
    """The local maps of one sequence and MapClosures' closures between them.

    ``map_poses`` are the poses the maps were built with (odometry); the
    ground truth places maps with ``gt_map_poses``, the ground-truth poses of
    each map's first scan (equal to ``map_poses`` with ``gt`` odometry).
    """

    scan_ranges: np.ndarray  # (M, 2) [first, last + 1) scan of each map, as its pipeline logs
    map_poses: np.ndarray  # (M, 4, 4) world pose of each map's frame
    points: list  # M arrays (K, 3), each in its map's frame
    closures: np.ndarray  # (C, 3) int64 ref, query, inliers
    closure_poses: np.ndarray  # (C, 4, 4) ref map frame -> query map frame
    gt_map_poses: np.ndarray | None = None  # (M, 4, 4) ground-truth pose of each map's frame


def build_maps(scans, poses: np.ndarray, params: MapClosuresParams | None = None,
               settings: NativeSettings | None = None, progress: bool = False) -> NativeMaps:
    """Run MapClosures' pipeline loop over ``scans`` placed with ``poses`` (module docstring).

    ``scans[i]`` is an ``(N, 3)`` array in frame ``i``'s LiDAR frame and
    ``poses`` the ``(N, 4, 4)`` LiDAR-frame poses.
    """
    params = MapClosuresParams() if params is None else params
    settings = NativeSettings() if settings is None else settings
    pb = backend.pybind()
    closer = backend.closer(params.closure_config())
    n = len(poses)
    gt_poses = np.asarray(poses, dtype=np.float64)
    kiss = _kiss_icp(settings.max_range) if settings.odometry == "kiss-icp" else None
    poses = np.empty_like(gt_poses) if kiss is not None else gt_poses
    vmap = pb._VoxelMap(float(params.density_map_resolution), float(settings.max_range))
    map_pose = np.eye(4) if kiss is not None else gt_poses[0].copy()
    start, ranges, map_poses, maps, closures, closure_poses = 0, [], [], [], [], []
    starts = []
    for i in tqdm(range(n), desc="mapclosures native", unit="scan", file=sys.stderr,
                  disable=not progress, leave=False):
        pts = np.asarray(scans[i], dtype=np.float64)
        if kiss is not None:  # its pipeline integrates KISS-ICP's (deskewed) frame
            pts, _ = kiss.register_frame(pts, np.empty(0))
            poses[i] = kiss.last_pose
        pts = pts[np.linalg.norm(pts, axis=1) < settings.max_range]
        frame_to_map = np.linalg.inv(map_pose) @ poses[i]
        vmap._integrate_frame(pb._Vector3dVector(pts), frame_to_map)
        if np.linalg.norm(frame_to_map[:3, 3]) > settings.map_range or i == n - 1:
            cloud = np.asarray(vmap._point_cloud(), dtype=np.float64).reshape(-1, 3)
            m = len(maps)
            for c in closer.get_closures(m, cloud):
                closures.append((c.source_id, c.target_id, c.number_of_inliers))
                closure_poses.append(np.asarray(c.pose, dtype=np.float64))
            ranges.append((start, i + 1))
            starts.append(start)
            map_poses.append(map_pose.copy())
            maps.append(cloud)
            vmap._remove_far_away_points(frame_to_map[:3, 3])
            keep = np.asarray(vmap._point_cloud(), dtype=np.float64).reshape(-1, 3)
            vmap._clear()
            vmap._integrate_frame(pb._Vector3dVector(keep), np.linalg.inv(poses[i]) @ map_pose)
            map_pose = np.asarray(poses[i], dtype=np.float64).copy()
            start = i
    return NativeMaps(np.asarray(ranges, np.int64).reshape(-1, 2), np.asarray(map_poses),
                      maps, np.asarray(closures, np.int64).reshape(-1, 3),
                      np.asarray(closure_poses, np.float64).reshape(-1, 4, 4),
                      gt_poses[np.asarray(starts, np.int64)])


def _kiss_icp(max_range: float):
    """KISS-ICP configured as MapClosures' pipeline does (1 m voxels, ``max_range``)."""
    backend.require()
    import importlib

    config = importlib.import_module("kiss_icp.config").KISSConfig()
    config.mapping.voxel_size = 1.0
    config.data.max_range = float(max_range)
    return importlib.import_module("kiss_icp.kiss_icp").KissICP(config)


def occupancy(points: np.ndarray, pose: np.ndarray, voxel: float) -> set:
    """The set of ``voxel`` m voxels (world frame) the points occupy."""
    world = np.asarray(points, np.float64) @ pose[:3, :3].T + pose[:3, 3]
    return set(map(tuple, np.floor(world / voxel).astype(np.int64)))


def overlap(a: set, b: set) -> float:
    """``|A ∩ B| / min(|A|, |B|)``; 0 when either is empty."""
    if not a or not b:
        return 0.0
    return len(a & b) / min(len(a), len(b))


def ground_truth_pairs(maps: NativeMaps, settings: NativeSettings | None = None
                       ) -> set[tuple[int, int]]:
    """Map pairs ``(a, b)``, ``a < b - 3``, whose occupancy overlap reaches ``settings.overlap``."""
    settings = NativeSettings() if settings is None else settings
    placed = maps.gt_map_poses if maps.gt_map_poses is not None else maps.map_poses
    occ = [occupancy(p, T, settings.overlap_voxel) for p, T in
           zip(maps.points, placed, strict=True)]
    return {(a, b) for b in range(len(occ)) for a in range(b - MAPS_SKIPPED)
            if overlap(occ[a], occ[b]) >= settings.overlap}


def pr_by_inliers(closures: np.ndarray, gt: set[tuple[int, int]]) -> list[dict[str, Any]]:
    """One row per inlier threshold ``t = 3 .. max``: TP, FP, FN, precision, recall, F1.

    Precision (recall) is None when no pair is predicted (no pair is true).
    """
    rows = []
    top = int(closures[:, 2].max()) if len(closures) else 3
    for t in range(3, max(top, 3) + 1):
        pred = {tuple(sorted((int(r), int(q)))) for r, q, k in closures if k >= t}
        tp = len(pred & gt)
        fp, fn = len(pred) - tp, len(gt) - tp
        p = tp / (tp + fp) if tp + fp else None
        r = tp / (tp + fn) if tp + fn else None
        f1 = 2 * p * r / (p + r) if p is not None and r is not None and p + r > 0 else \
            (0.0 if p is not None and r is not None else None)
        rows.append({"inliers_threshold": t, "tp": tp, "fp": fp, "fn": fn,
                     "precision": p, "recall": r, "f1": f1})
    return rows


def pose_errors(maps: NativeMaps, gt: set[tuple[int, int]]) -> dict[str, Any]:
    """Median translation (m) and rotation (deg) errors of the true closures' poses."""
    rte, rre = [], []
    for (r, q, _), T in zip(maps.closures, maps.closure_poses, strict=True):
        if (int(r), int(q)) not in gt:
            continue
        placed = maps.gt_map_poses if maps.gt_map_poses is not None else maps.map_poses
        truth = np.linalg.inv(placed[q]) @ placed[r]
        d = np.linalg.inv(truth) @ T
        rte.append(float(np.linalg.norm(d[:3, 3])))
        rre.append(float(np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))))
    def med(values: list) -> float | None:
        return float(np.median(values)) if values else None

    return {"n_true_closures": len(rte), "median_rte_m": med(rte), "median_rre_deg": med(rre)}


def evaluate_native(scans, poses: np.ndarray, params: MapClosuresParams | None = None,
                    settings: NativeSettings | None = None, progress: bool = False
                    ) -> dict[str, Any]:
    """Native mode end to end: maps, closures, ground truth, metrics (a JSON-ready dict)."""
    params = MapClosuresParams() if params is None else params
    settings = NativeSettings() if settings is None else settings
    maps = build_maps(scans, poses, params, settings, progress)
    gt = ground_truth_pairs(maps, settings)
    rows = pr_by_inliers(maps.closures, gt)
    f1s = [r["f1"] for r in rows if r["f1"] is not None]
    accept = params.inliers_threshold + 1
    at_accept = next((r for r in rows if r["inliers_threshold"] == accept), None)
    return {
        "method": "mapclosures", "mode": "native", "map_closures": backend.PINNED_VERSION,
        "params": asdict(params), "native": asdict(settings), "odometry": settings.odometry,
        "n_scans": len(poses), "n_maps": len(maps.points),
        "scan_ranges": maps.scan_ranges.tolist(),
        "ground_truth": {"n_pairs": len(gt), "pairs": sorted(map(list, gt)),
                         "rule": f"maps a < b - {MAPS_SKIPPED} whose world-frame occupancy "
                                 f"({settings.overlap_voxel} m voxels) overlaps "
                                 f">= {settings.overlap} of the smaller map"},
        "closures": maps.closures.tolist(),
        "f1_max": max(f1s) if f1s else None,
        "at_pipeline_acceptance": at_accept,
        "pr_by_inliers": rows,
        **pose_errors(maps, gt),
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m lidar_iris_eval.descriptors.mapclosures.native SEQ [--out F]``; exit code."""
    import click

    from lidar_iris_eval.errors import LirisError

    @click.command()
    @click.argument("sequence", type=click.Path(exists=True, file_okay=False))
    @click.option("--out", type=click.Path(dir_okay=False), default=None,
                  help="Write the result JSON here (default: stdout).")
    @click.option("--map-range", type=float, default=NativeSettings.map_range, show_default=True,
                  help="Close a local map this far (m) from its first pose.")
    @click.option("--overlap", type=float, default=NativeSettings.overlap, show_default=True,
                  help="Ground truth: occupancy overlap of a true map pair.")
    @click.option("--odometry", type=click.Choice(ODOMETRY), default="gt", show_default=True,
                  help="Scan poses: the sequence's, or KISS-ICP's as MapClosures' pipeline.")
    @click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
    def cli(sequence, out, map_range, overlap, odometry, quiet):
        from lidar_iris_eval.io import open_sequence

        backend.require()
        if not map_range > 0:
            raise LirisError("--map-range", f"must be positive, got {map_range}")
        if not 0 < overlap <= 1:
            raise LirisError("--overlap", f"must be in (0, 1], got {overlap}")
        seq = open_sequence(sequence)
        scans = (seq[i] for i in range(len(seq)))
        result = evaluate_native(list(scans) if len(seq) < 2 else _Lazy(seq), seq.poses,
                                 settings=NativeSettings(map_range=map_range, overlap=overlap,
                                                         odometry=odometry),
                                 progress=not quiet)
        text = json.dumps(result, indent=1)
        if out is None:
            click.echo(text)
        else:
            _write_atomic(Path(out), text)
            best = result["f1_max"]
            click.echo(f"{result['n_maps']} local maps, {len(result['closures'])} closures, "
                       f"{result['ground_truth']['n_pairs']} true map pairs; F1max "
                       f"{'n/a' if best is None else f'{best:.3f}'} -> {out}", err=True)

    try:
        cli.main(args=argv, prog_name="mapclosures-native", standalone_mode=False)
    except LirisError as err:
        click.echo(f"liris: error: {err}", err=True)
        return 2
    except click.ClickException as err:
        err.show()
        return 2
    return 0


class _Lazy:
    """``seq[i]`` read when asked for, so memory holds one scan at a time."""

    def __init__(self, seq):
        self.seq = seq

    def __len__(self) -> int:
        return len(self.seq)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.seq[i]


def _write_atomic(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text + "\n")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


if __name__ == "__main__":
    sys.exit(main())
