"""``liris gt``: ground-truth counts from poses alone."""

from __future__ import annotations

import sys
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from lidar_iris_eval.cli.options import current_convention, ground_truth_options, parse_exclude
from lidar_iris_eval.cli.output import echo_json, echo_table
from lidar_iris_eval.cli.sequence_options import sequence_options
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.errors import options as option_names
from lidar_iris_eval.evaluation.conventions import convention_counts, with_overrides
from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
from lidar_iris_eval.io.poses import camera_to_lidar, read_calib, read_pose_file


@click.command("gt")
@click.argument("sequence", required=False, type=click.Path(path_type=Path))
@click.option("--poses", "poses_path", type=click.Path(path_type=Path),
              help="Pose file (KITTI 3x4 or TUM); enough on its own, no scans needed.")
@click.option("--calib", "calib_path", type=click.Path(path_type=Path),
              help="KITTI calib.txt with Tr, for LiDAR-frame distances from camera poses.")
@ground_truth_options
@sequence_options
@click.option("--check-scans", is_flag=True,
              help="Also read every scan of SEQUENCE and report point counts (slow on KITTI).")
@click.option("--gt", "gt_kind", type=click.Choice(["pose", "overlap"]), default="pose",
              show_default=True,
              help="overlap: also OverlapNet-style range-image overlap >= 0.3 from the scans "
                   "(cached; docs/cross-session.md), with its agreement with pose distance.")
@click.option("--cache-dir", type=click.Path(path_type=Path), default=None,
              help="Where the overlap matrix is cached [default: $LIRIS_CACHE_DIR or "
                   "./.liris-cache].")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def command(sequence, poses_path, calib_path, radius, exclude, distance, pose_frame, check_scans,
            gt_kind, cache_dir, as_json, reader_options):
    """Count positive pairs and revisit queries of SEQUENCE (or of --poses).

    Pairs are ordered pairs (i, j), i != j, positive when closer than --radius;
    a revisit query has a positive partner at least --exclude frames earlier.
    """
    conv = current_convention()  # --convention (issue 17): per-query rules, windows in seconds
    seconds = conv.exclude_seconds is not None
    exclude_frames, exclude_name = (1, "seconds") if seconds else parse_exclude(exclude)
    positions, source, seq, pose_frame = _positions(
        sequence, poses_path, calib_path, pose_frame, reader_options
    )
    gt = compute_ground_truth(positions, radius, exclude_frames, distance, pose_frame)
    if exclude_name == "custom" and conv.name not in ("liris", "custom"):
        exclude_name = f"convention {conv.name}"  # E came from the convention, not from --exclude
    summary = {"source": str(source), **gt.summary(), "exclude_preset": exclude_name}
    conv = with_overrides(conv, pose_frame=pose_frame)
    counts = convention_counts(positions, conv, getattr(seq, "times", None))
    if conv.name == "liris":  # gt.summary() already counted; keep its numbers, add the keys
        counts = {k: v for k, v in counts.items() if k not in summary}
    summary.update(counts)
    if check_scans:
        if seq is None:
            raise LirisError("--check-scans", "needs a SEQUENCE folder, not only --poses")
        summary.update(_scan_statistics(seq))
    if gt_kind == "overlap":
        if seq is None:
            raise LirisError("--gt overlap", "needs a SEQUENCE folder (the scans), not only "
                                             "--poses")
        summary.update(_overlap_summary(seq, gt, exclude_frames, cache_dir))
    if as_json:
        echo_json(summary)
    else:
        echo_table([summary])


def _positions(sequence, poses_path, calib_path, pose_frame, reader_options):
    """Translations, source and frame used, from a sequence or a bare pose file."""
    if sequence is None and poses_path is None:
        raise LirisError("liris gt", "give a SEQUENCE folder or --poses FILE")
    if sequence is not None:
        from lidar_iris_eval.io import open_sequence

        seq = open_sequence(sequence, poses=poses_path, calib=calib_path, **reader_options)
        if reader_options.get("lidar_frame") and not _given("pose_frame"):
            pose_frame = "lidar"  # the poses are LiDAR poses: nothing to fall back from
        pose_frame = seq.resolve_pose_frame(pose_frame)
        return seq.positions(pose_frame), sequence, seq, pose_frame
    if reader_options:
        raise LirisError(option_names(reader_options), "needs a SEQUENCE, not only --poses")
    _, poses = read_pose_file(poses_path)
    if pose_frame == "lidar":
        if calib_path is None:
            raise LirisError("--pose-frame lidar", "needs --calib to convert camera poses")
        poses = camera_to_lidar(poses, read_calib(calib_path))
    return poses[:, :3, 3], poses_path, None, pose_frame


def _given(name: str) -> bool:
    """True when option ``name`` was set on the command line (not a default)."""
    ctx = click.get_current_context(silent=True)
    if ctx is None:
        return False
    return ctx.get_parameter_source(name) == click.core.ParameterSource.COMMANDLINE


def _scan_statistics(seq) -> dict:
    """Read every scan (so bad files surface now) and summarise point counts."""
    counts = np.array(
        [len(seq[i]) for i in tqdm(range(len(seq)), desc="reading scans", unit="scan",
                                   file=sys.stderr, disable=None)]
    )
    return {
        "scans_read": int(len(counts)),
        "points_min": int(counts.min()),
        "points_median": int(np.median(counts)),
        "points_max": int(counts.max()),
    }


def _overlap_summary(seq, gt, exclude: int, cache_dir) -> dict:
    """Overlap ground-truth counts and their agreement with the pose-distance ones."""
    from lidar_iris_eval.evaluation.overlap import (
        OverlapSpec,
        cached_overlap_matrix,
        overlap_ground_truth,
    )

    spec = OverlapSpec()
    matrix, hit = cached_overlap_matrix(seq, cache_dir, spec, progress=True)
    ogt = overlap_ground_truth(matrix, exclude, spec)
    pose_pairs = {tuple(p) for p in gt.pairs.tolist()}
    overlap_pairs = {tuple(p) for p in ogt.pairs.tolist()}
    both = len(pose_pairs & overlap_pairs)
    return {
        "overlap_rule": f"range-image overlap >= {spec.threshold:g} (later frame as query; "
                        f"{spec.height}x{spec.width}, {spec.fov_up_deg:g}/{spec.fov_down_deg:g} "
                        f"deg, {spec.max_range:g} m, |dr| < {spec.range_tolerance:g} m)",
        "overlap_positive_pairs": len(overlap_pairs),
        "overlap_revisit_queries": ogt.n_revisits,
        "pairs_positive_under_both": both,
        "share_of_pose_pairs_with_overlap": both / len(pose_pairs) if pose_pairs else None,
        "share_of_overlap_pairs_within_radius": both / len(overlap_pairs) if overlap_pairs
        else None,
        "overlap_from_cache": hit,
    }
