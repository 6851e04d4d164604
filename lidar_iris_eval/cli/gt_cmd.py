"""``liris gt``: ground-truth counts from poses alone."""

from __future__ import annotations

import sys
from pathlib import Path

import click
import numpy as np
from tqdm import tqdm

from lidar_iris_eval.atomic import figure_format
from lidar_iris_eval.cli.options import current_convention, ground_truth_options
from lidar_iris_eval.cli.output import check_output_file, echo_json, echo_table, format_value
from lidar_iris_eval.cli.sequence_options import sequence_options
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.errors import options as option_names
from lidar_iris_eval.evaluation.conventions import convention_counts
from lidar_iris_eval.evaluation.ground_truth import compute_ground_truth
from lidar_iris_eval.evaluation.settings import Settings
from lidar_iris_eval.io.poses import camera_to_lidar, read_calib, read_pose_file
from lidar_iris_eval.ownership import check_new_files


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
@click.option("--explain", "explain", type=int, nargs=2, default=None, metavar="I J",
              help="Explain one pair: distances (3-D, planar; camera and LiDAR frame), frames "
                   "and seconds apart, overlap when scans are there, and for every convention "
                   "preset whether it is a positive and whether I is a revisit query, naming "
                   "the deciding rule (docs/conventions.md).")
@click.option("--diff", "diff", nargs=2, default=None, metavar="A B",
              help="The positive pairs and revisit queries that convention A has and B lacks, "
                   "and the reverse (counts; --diff-csv, --diff-plot). A or B may change a "
                   "preset's rules: scancontext-eval:radius=4 (radius, exclude, distance, "
                   "pose_frame).")
@click.option("--diff-csv", type=click.Path(path_type=Path), default=None,
              help="With --diff: write every differing query and pair, with the rule, to this CSV.")
@click.option("--diff-plot", type=click.Path(path_type=Path), default=None,
              help="With --diff: the trajectory with the differing revisit queries marked "
                   "(.png/.pdf/.svg).")
@click.option("--overwrite", is_flag=True, help="Replace an existing --diff-csv / --diff-plot.")
@click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")
def command(sequence, poses_path, calib_path, radius, exclude, distance, pose_frame, check_scans,
            gt_kind, cache_dir, explain, diff, diff_csv, diff_plot, overwrite, as_json,
            reader_options):
    """Count positive pairs and revisit queries of SEQUENCE (or of --poses).

    Pairs are ordered pairs (i, j), i != j, positive when closer than --radius;
    a revisit query has a positive partner at least --exclude frames earlier.
    """
    if explain is not None or diff is not None:
        if check_scans or gt_kind != "pose":
            raise LirisError("--check-scans" if check_scans else "--gt overlap",
                             "not with --explain / --diff (--explain reports the pair's overlap "
                             "when the scans are there)")
        return _explain_or_diff(sequence, poses_path, calib_path, explain, diff, diff_csv,
                                diff_plot, overwrite, as_json, reader_options)
    if diff_csv is not None or diff_plot is not None:
        raise LirisError("--diff-csv/--diff-plot", "only with --diff A B")
    # --convention (issue 17) and the ground-truth options, parsed once (Settings.from_options)
    conv = current_convention()
    seconds = conv.exclude_seconds is not None
    exclude_frames, exclude_name = (1, "seconds") if seconds else (conv.exclude,
                                                                    conv.exclude_name)
    positions, source, seq, pose_frame = _positions(
        sequence, poses_path, calib_path, conv.pose_frame, reader_options
    )
    gt = compute_ground_truth(positions, conv.radius, exclude_frames, conv.distance, pose_frame)
    if exclude_name == "custom" and conv.name not in ("liris", "custom"):
        exclude_name = f"convention {conv.name}"  # E came from the convention, not from --exclude
    summary = {"source": str(source), **gt.summary(), "exclude_preset": exclude_name}
    if pose_frame != conv.pose_frame:  # the sequence has LiDAR poses only: merged like an option
        conv = Settings.from_options(conv, pose_frame=pose_frame)
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


def _explain_or_diff(sequence, poses_path, calib_path, explain, diff, diff_csv, diff_plot,
                     overwrite, as_json, reader_options):
    """``--explain I J`` or ``--diff A B`` (lidar_iris_eval.evaluation.explain)."""
    from lidar_iris_eval.evaluation import explain as ex

    given = [f"--{n}" for n in ("radius", "exclude", "distance", "pose_frame", "convention_name")
             if _given(n)]
    if given:
        raise LirisError(given[0].replace("_", "-").replace("-name", ""),
                         "--explain and --diff use every preset's own rules; leave it out")
    if explain is not None and diff is not None:
        raise LirisError("--explain", "give --explain or --diff, not both")
    if explain is not None and (diff_csv is not None or diff_plot is not None):
        raise LirisError("--diff-csv/--diff-plot", "only with --diff A B")
    if diff is not None:
        for flag, name in zip(("A", "B"), diff, strict=True):
            ex.preset_named(name, f"--diff {flag}=")  # fails before the poses are read
        if diff[0] == diff[1]:
            raise LirisError(f"--diff {diff[0]} {diff[1]}", "give two different conventions")
        outputs = [p for p in (diff_csv, diff_plot) if p is not None]
        if diff_plot is not None:
            figure_format(diff_plot, "--diff-plot")
        for path, flag in ((diff_csv, "--diff-csv"), (diff_plot, "--diff-plot")):
            if path is not None:
                check_output_file(path, flag)
        check_new_files(outputs, overwrite, "--diff-csv/--diff-plot",
                        inputs=[p for p in (sequence, poses_path, calib_path) if p is not None])
    traj = ex.load_trajectory(sequence, poses_path, calib_path, reader_options)
    if explain is not None:
        result = ex.explain_pair(traj, *explain)
        if as_json:
            echo_json(result)
        else:
            _echo_explain(result)
        return None
    result = ex.diff_conventions(traj, *diff)
    summary = {"source": traj.source, "frames": traj.n_frames, **result.summary()}
    if diff_csv is not None:
        summary["diff_csv"] = str(diff_csv)
        summary["diff_csv_rows"] = ex.write_diff_csv(result, diff_csv)
    if diff_plot is not None:
        from lidar_iris_eval.plotting.convention_diff import plot_convention_diff

        summary["diff_plot"] = plot_convention_diff(result, diff_plot)
    if as_json:
        echo_json(summary)
    else:
        echo_table([{k: v for k, v in summary.items()}])
    return None


def _echo_explain(result: dict) -> None:
    """``--explain`` as text: the pair, then one line per preset with its deciding rule."""
    pair = result["pair"]
    click.echo(f"pair {pair['i']} - {pair['j']} of {result['source']} ({result['frames']} frames)")
    for key, value in pair.items():
        if key not in ("i", "j"):
            click.echo(f"  {key}: {format_value(value)}")
    rows = [{"convention": r["convention"], "pair": r["status"],
             f"I={pair['i']} revisit query": r["i_revisit_query"],
             "radius": r["radius_m"], "window": r["window"], "distance": r["distance"],
             "frame": r["pose_frame"]} for r in result["conventions"]]
    echo_table(rows)
    click.echo("")
    for r in result["conventions"]:
        click.echo(f"{r['convention']}: {r['status']} - {r['rule']}")
        click.echo(f"{' ' * len(r['convention'])}  {pair['i']} as a query: {r['i_rule']}")


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
