"""From a run directory to figures: one builder per figure, and the drivers.

Each ``build_*`` function reads what it needs from a
:class:`~lidar_iris_eval.runs.reader.Run` (the one reader of run folders) and returns a
:class:`~matplotlib.figure.Figure` (or ``None`` with a warning when an
optional input is missing), so callers and tests can inspect the plotted
data before anything is written. :func:`plot_run` and :func:`plot_compare`
write them under stable names.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from lidar_iris_eval.errors import LirisError, LirisWarning, warn
from lidar_iris_eval.plotting import style
from lidar_iris_eval.plotting.affinity import affinity_figure
from lidar_iris_eval.plotting.pr import pr_figure, protocol_title, run_curves
from lidar_iris_eval.plotting.timing import timing_figure
from lidar_iris_eval.plotting.trajectory import Outcomes, outcomes, trajectory_figure
from lidar_iris_eval.runs.reader import Run, load_run

#: figure name -> file stem; stable, because the README links to them
FILE_STEMS = {
    "pr1": "pr_protocol1",
    "pr2": "pr_protocol2",
    "affinity": "affinity",
    "trajectory": "trajectory",
    "timing": "timing",
    "iris_frame": "iris_frame",
    "iris_alignment": "iris_alignment",
    "recall": "recall_at_n",
    "pr_cross": "pr_cross_session",
    "loops": "loops_trajectory",
    "posegraph": "posegraph_ape",
}
IRIS = "lidar-iris"


# ---- builders -------------------------------------------------------------------------
def build_pr(run: Run, protocol: int) -> Figure | None:
    """All methods' PR curves for one protocol, or None when the run lacks it."""
    if protocol not in run.protocols():
        return None
    exclude = run.gt_settings().exclude if protocol == 1 else None
    return pr_figure(run_curves(run, protocol), protocol_title(protocol, exclude))


def build_pr_compare(runs: Sequence[Run], protocol: int) -> Figure | None:
    """PR curves of several runs overlaid; colour = method, line style = run."""
    curves = []
    for k, run in enumerate(runs):
        if protocol in run.protocols():
            dash = style.RUN_LINESTYLES[k % len(style.RUN_LINESTYLES)]
            curves += run_curves(run, protocol, prefix=run.name, linestyle=dash)
    if not curves:
        return None
    return pr_figure(curves, protocol_title(protocol), legend_outside=True)


def build_affinity(run: Run) -> Figure | None:
    """Ground truth beside each protocol 2 affinity matrix.

    Above 8192 frames a run keeps only ``affinity_decimated.npy`` (every k-th
    frame): the figure is then drawn on those frames, ground truth included,
    and says "decimated by k".
    """
    matrices, steps = {}, {}
    for name in style.in_method_order(run.descriptors(2)):
        found = run.affinity_for_figures(name)
        if found is None:
            warn(run.path / "protocol2" / name,
                 "no affinity.npy or affinity_decimated.npy; left out of affinity figure")
        else:
            matrices[name], steps[name] = found
    if not matrices:
        return None
    step = max(steps.values())  # one run has one frame count, so one decimation step
    shown = {name: m if steps[name] == step else m[::step, ::step]
             for name, m in matrices.items()}
    return affinity_figure(run.ground_truth(step).positive_matrix(), shown,
                           radius=run.gt_settings().radius, step=step,
                           n_frames=run.n_frames)


def build_trajectory(run: Run) -> Figure:
    """The path with revisits, and protocol 1 detections at each method's F1max τ."""
    from lidar_iris_eval.evaluation.ground_truth import ground_plane_axes

    settings = run.gt_settings()
    results: dict[str, Outcomes] = {}
    for name in style.in_method_order(run.descriptors(1)):
        matches = run.matches(name, required=False)
        tau = _number(run.row(1, name).get("f1_threshold"))
        if matches is None or math.isnan(tau):
            warn(run.path / "protocol1" / name,
                 "no matches.csv or f1_threshold; left out of trajectory figure")
            continue
        results[name] = outcomes(matches, tau)
    return trajectory_figure(run.positions(), ground_plane_axes(settings.pose_frame),
                             run.ground_truth().revisit, results, frame=settings.pose_frame)


def build_loops(run: Run) -> tuple[Figure | None, Figure | None]:
    """A ``--loops`` run's loops on the trajectory, and its pose-graph APE bars (or None)."""
    from lidar_iris_eval.evaluation.ground_truth import ground_plane_axes
    from lidar_iris_eval.plotting.loops import loops_figure, posegraph_figure

    tables = run.loop_tables("loops")
    if not tables:
        return None, None
    settings = run.gt_settings()
    trajectory = loops_figure(run.positions(), ground_plane_axes(settings.pose_frame),
                              run.ground_truth().revisit, tables, frame=settings.pose_frame)
    graphs = run.loop_tables("posegraph")
    for name, table in graphs.items():  # label each false loop by its frames
        loops = tables.get(name)
        if loops is not None and "loop" in table.columns:
            k = table["loop"].to_numpy(dtype=np.int64)
            ok = (k >= 0) & (k < len(loops))
            table = table.copy()
            table["query"] = np.where(ok, loops["query"].to_numpy()[np.clip(k, 0, None)], -1)
            table["match"] = np.where(ok, loops["match"].to_numpy()[np.clip(k, 0, None)], -1)
            graphs[name] = table
    return trajectory, (posegraph_figure(graphs) if graphs else None)


def build_timing(run: Run) -> Figure | None:
    """Per-scan extraction times (box) and matching time per method (bar)."""
    extract = {}
    for name in style.in_method_order(run.descriptors()):
        table = run.timing(name, required=False)
        if table is not None:
            extract[name] = table["extract_s"].to_numpy(dtype=np.float64) * 1e3
    match, label = {}, "matching [ms / query]"
    if run.descriptors(2):
        match = {n: _number(run.row(2, n).get("match_us_per_pair"))
                 for n in style.in_method_order(run.descriptors(2))}
        label = "matching [µs / pair]"
    if not any(np.isfinite(v) for v in match.values()):
        match = {n: _number(run.row(1, n).get("match_ms_per_query"))
                 for n in style.in_method_order(run.descriptors(1))}
        label = "matching [ms / query]"
    if not extract and not any(np.isfinite(v) for v in match.values()):
        return None
    return timing_figure(extract, match, label, _conditions(run))


def _conditions(run: Run) -> str:
    """``"2 cores, load average 11.7 (1 min) at the end of the run"``, when recorded."""
    host = run.metrics.get("host") or {}
    load = host.get("load_average_1_5_15min")
    if not load:
        return ""
    cores = host.get("cpu_count")
    where = f"{cores} cores, " if cores else ""
    return f"{where}load average {load[0]:.1f} at the end of the run (matching is wall time)"


def build_iris(run: Run, frame: int | None = None) -> tuple[Figure | None, Figure | None]:
    """LiDAR Iris image + binary maps of one frame, and the alignment of a revisit pair.

    Needs the scans (``sequence`` in config.yaml) and the LiDAR Iris module;
    without them both figures are skipped with a warning. ``frame`` defaults
    to an illustrative revisit (see :func:`_default_iris_frame`); its partner
    is the frame LiDAR Iris matched in protocol 1 when that match is true, else
    the nearest earlier frame allowed by the exclusion window.
    """
    n = run.n_frames
    if frame is not None and not 0 <= frame < n:
        raise LirisError(f"--frame {frame}", f"frame index out of range (run has {n} frames)")
    gt = run.ground_truth()
    revisits = np.flatnonzero(gt.revisit)
    if frame is None:
        frame = _default_iris_frame(run)
    if frame is None:
        frame = int(revisits[0]) if len(revisits) else 0
    sequence = _open_run_sequence(run)
    if sequence is None:
        return None, None
    try:
        from lidar_iris_eval.descriptors import lidar_iris
        from lidar_iris_eval.plotting.iris_figures import iris_alignment_figure, iris_frame_figure
    except ImportError as err:
        warn(run.path, f"LiDAR Iris figures skipped: {err}")
        return None, None
    desc = _iris_descriptor(run)
    params = desc.params
    image = lidar_iris.iris_image(sequence[frame], params)
    features, mask = lidar_iris.binary_features(image, params)
    frame_fig = iris_frame_figure(image, features, mask, _wavelengths(params),
                                  _scan_id(sequence, frame))
    partner = _true_iris_match(run, frame)
    if partner is None:
        partner = _revisit_partner(run, frame, gt)
    if partner is None:
        warn(f"--frame {frame}", "not a revisit query (no earlier frame within the radius "
             f"and outside E = {gt.exclude}); alignment figure skipped")
        return frame_fig, None
    other = lidar_iris.iris_image(sequence[partner], params)
    dist, yaw = desc.distance(desc.compute(sequence[frame]), desc.compute(sequence[partner]))
    if not np.isfinite(yaw):
        warn(f"--frame {frame}", f"no yaw estimate against frame {partner} (every feature bit "
             "masked); alignment figure skipped")
        return frame_fig, None
    align_fig = iris_alignment_figure(image, other, yaw, dist,
                                      (_scan_id(sequence, frame), _scan_id(sequence, partner)))
    return frame_fig, align_fig


# ---- drivers ----------------------------------------------------------------------------
def plot_run(run_dir: str | Path, out_dir: str | Path | None = None, fmt: str = "png",
             frame: int | None = None, failures: int | None = None) -> list[Path]:
    """Write every figure of one run; returns the files written.

    ``failures=N`` adds the failure atlas (:mod:`~lidar_iris_eval.plotting.atlas`):
    ``failures_<descriptor>`` per protocol 1 method.

    ``out_dir`` defaults to ``<run_dir>/figures``; figures already there are
    replaced (they are derived outputs). In any other folder, replacing an
    existing file is announced with a warning.
    """
    fmt = _check_format(fmt)
    run = load_run(run_dir)
    if not run.rows:
        raise LirisError(run.path / "metrics.json", "no results to plot")
    if frame is not None and not 0 <= frame < run.n_frames:
        raise LirisError(f"--frame {frame}",
                         f"frame index out of range (run has {run.n_frames} frames)")
    if failures is not None and failures < 1:
        raise LirisError(f"--failures {failures}", "must be at least 1")
    default_out = out_dir is None
    out = Path(run.path / "figures" if default_out else out_dir)
    from lidar_iris_eval.plotting.recall import build_recall

    if run.config.get("kind") == "cross-session":  # no trajectory, affinity or Iris frames
        curves = run_curves(run, "cross-session")
        return _write({"recall": build_recall(run),
                       "pr_cross": pr_figure(curves, "cross-session, top-1 per query")},
                      out, fmt, warn_overwrite=not default_out)
    figures: dict[str, Figure | None] = {
        "pr1": build_pr(run, 1),
        "pr2": build_pr(run, 2),
        "affinity": build_affinity(run),
        "trajectory": build_trajectory(run),
        # a --loops run extracted and matched nothing: no timing to show
        "timing": None if run.loop_tables("loops") else build_timing(run),
    }
    # only for a run that scored LiDAR Iris: a GOSMatch or ESM run's figures must not
    # show another method's internals as if they were its own
    if IRIS in run.descriptors():
        figures["iris_frame"], figures["iris_alignment"] = build_iris(run, frame)
    figures["recall"] = build_recall(run)  # with --ranking
    figures["loops"], figures["posegraph"] = build_loops(run)  # a --loops run
    if failures is not None:
        from lidar_iris_eval.plotting.atlas import build_failures

        figures.update(build_failures(run, failures, _open_run_sequence))
    return _write(figures, out, fmt, warn_overwrite=not default_out)


def plot_compare(run_dirs: Sequence[str | Path], out_dir: str | Path | None = None,
                 fmt: str = "png") -> list[Path]:
    """Overlay the PR curves of several runs (labels ``"<run>: <descriptor>"``).

    ``out_dir`` defaults to ``compare-<run>-…/`` next to the first run.
    """
    fmt = _check_format(fmt)
    if len(run_dirs) < 2:
        raise LirisError("--compare", "give at least two results directories")
    runs = [load_run(p) for p in run_dirs]
    names = [r.name for r in runs]
    if len(set(names)) < len(names):  # same folder name in different places: use parents
        for run in runs:
            run.name = f"{run.path.parent.name}/{run.path.name}"
    default_out = out_dir is None
    out = Path(runs[0].path.parent / ("compare-" + "-".join(r.path.name for r in runs))
               if default_out else out_dir)
    figures = {"pr1": build_pr_compare(runs, 1), "pr2": build_pr_compare(runs, 2)}
    return _write(figures, out, fmt, warn_overwrite=not default_out)


def figure_path(out_dir: Path, key: str, fmt: str) -> Path:
    return Path(out_dir) / f"{FILE_STEMS.get(key, key)}.{fmt}"


# ---- helpers --------------------------------------------------------------------------
def _write(figures: dict[str, Figure | None], out: Path, fmt: str,
           warn_overwrite: bool) -> list[Path]:
    if out.exists() and not out.is_dir():
        raise LirisError(out, "output path exists and is not a folder")
    written = []
    # every figure also as vector PDF, the format a paper needs, beside a raster one
    formats = [fmt] if fmt in style.VECTOR_FORMATS else [fmt, "pdf"]
    for key, fig in figures.items():
        if fig is None:
            continue
        for each in formats:
            path = figure_path(out, key, each)
            if warn_overwrite and path.exists():
                warn(path, "replacing existing figure")
            written.append(style.save(fig, path))
    return written


def _check_format(fmt: str) -> str:
    fmt = fmt.lower().lstrip(".")
    if fmt not in style.FORMATS:
        raise LirisError(f"--format {fmt}", f"choose one of {', '.join(style.FORMATS)}")
    return fmt


def _number(value) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _open_run_sequence(run: Run):
    """The run's sequence, or None (with a warning) when it cannot be used."""
    path = run.sequence_path
    if path is None:
        warn(run.path / "config.yaml", "no sequence path; LiDAR Iris figures skipped")
        return None
    if not path.is_absolute() and not path.exists() and (run.path / path).exists():
        path = run.path / path
    if not path.exists():
        warn(path, "sequence not found; LiDAR Iris figures skipped")
        return None
    from lidar_iris_eval.io import open_sequence

    try:  # with the run's recorded --poses, --lidar-frame-poses, ... (issue 15)
        sequence = open_sequence(path, **_recorded_reader_options(run))
    except LirisError as err:
        warn(path, f"cannot open sequence ({err.problem}); LiDAR Iris figures skipped")
        return None
    if len(sequence) != run.n_frames:
        warn(path, f"has {len(sequence)} scans but the run has {run.n_frames} frames; "
             "LiDAR Iris figures skipped")
        return None
    return sequence


#: the run's sequence for figures that need the scans (the failure atlas of ``liris report``)
open_run_sequence = _open_run_sequence


def _recorded_reader_options(run: Run) -> dict:
    """The reader options config.yaml records, typed again (old runs stored strings)."""
    recorded = (run.config.get("sequence") or {}).get("reader_options") or {}
    typed = {"lidar_frame": lambda v: v if isinstance(v, bool) else str(v) == "True",
             "tolerance": float, "min_distance": float, "every": int}
    return {k: (typed[k](v) if k in typed and v is not None else v) for k, v in recorded.items()}


def _scan_id(sequence, index: int) -> str:
    """The scan's own name (file stem or recorded frame id), not its index in the run."""
    paths = getattr(sequence, "scan_paths", None)
    if paths:
        return Path(paths[index]).stem
    ids = getattr(sequence, "frame_ids", None)
    if ids is not None and len(ids) > index:
        return str(int(ids[index]))
    return str(index)


def _iris_descriptor(run: Run):
    """LiDAR Iris with the run's preset and parameters (so figures show what was scored),
    or the default preset when the run did not evaluate it."""
    from lidar_iris_eval.descriptors import get_descriptor

    preset, params = run.descriptor_params(IRIS)
    try:
        # config.yaml records every parameter, set by the user or not; a figure
        # must not warn that shift_window is ignored when nobody set it (the
        # run's own eval warned already when somebody did)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=r".*ignored: ", category=LirisWarning)
            return get_descriptor(IRIS, preset=preset, **params)
    except LirisError as err:
        warn(run.path / "config.yaml", f"{err.problem}; using the default LiDAR Iris preset")
        return get_descriptor(IRIS)


def _wavelengths(params) -> list[float] | None:
    """Filter wavelengths λ_s = minWaveLength · mult^s, when the params expose them."""
    nscale = getattr(params, "nscale", None)
    base = getattr(params, "min_wavelength", None) or getattr(params, "min_wave_length", None)
    mult = getattr(params, "mult", None)
    if nscale is None or base is None or mult is None:
        return None
    return [float(base) * float(mult) ** s for s in range(int(nscale))]


def _true_iris_matches(run: Run):
    """LiDAR Iris protocol 1 rows whose best match is a true loop, or None."""
    table = run.matches(IRIS, required=False) if IRIS in run.descriptors(1) else None
    if table is None or table.empty:
        return None
    return table[table["is_true"].astype(bool) & table["is_revisit"].astype(bool)]


def _default_iris_frame(run: Run) -> int | None:
    """A revisit that shows what the alignment does, like the paper's Fig. 5.

    The first revisit query often sits where a loop closes at a junction,
    next to a frame seen from a side street: a poor illustration. Prefer a
    true LiDAR Iris match made in the reverse direction (yaw near 180°), the
    case Iris handles and M2DP cannot, else the best true match.
    """
    rows = _true_iris_matches(run)
    if rows is None or rows.empty:
        return None
    reverse = rows[np.abs(rows["yaw_deg"].to_numpy(dtype=float) - 180.0) < 45.0]
    pool = reverse if not reverse.empty else rows
    return int(pool.loc[pool["distance"].idxmin(), "query"])


def _true_iris_match(run: Run, frame: int) -> int | None:
    """The frame LiDAR Iris matched to ``frame`` in protocol 1, when it is a true loop."""
    rows = _true_iris_matches(run)
    if rows is None:
        return None
    hit = rows[rows["query"] == frame]
    return None if hit.empty else int(hit["match"].iloc[0])


def _revisit_partner(run: Run, frame: int, gt) -> int | None:
    """Nearest frame j ≤ frame − E within the radius, or None."""
    from lidar_iris_eval.evaluation.ground_truth import gt_coordinates

    last = frame - gt.exclude
    if last < 0:
        return None
    s = run.gt_settings()
    coords = gt_coordinates(run.positions(), s.pose_frame, s.distance)
    dist = np.linalg.norm(coords[: last + 1] - coords[frame], axis=1)
    best = int(np.argmin(dist))
    return best if dist[best] < s.radius else None

