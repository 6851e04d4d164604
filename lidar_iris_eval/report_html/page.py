"""One HTML page that shows a run folder: interactive PR curves, affinity images,
the trajectory with protocol 1 outcomes, the metrics table and the conventions.

The page works offline and from a plain file: plotly's JavaScript is written
beside it (``plotly.min.js``), never loaded from a CDN, and the affinity
matrices are embedded as PNG images (an ``(N, N)`` matrix as JSON would be
hundreds of megabytes at KITTI scale). Nothing is recomputed: every number
comes from the run folder. plotly is an optional dependency (extra
``report``); without it :func:`build_report` says how to install it.
"""

from __future__ import annotations

import base64
import html
import io
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, os_error
from lidar_iris_eval.ownership import check_replaceable, replace_folder, write_manifest
from lidar_iris_eval.plotting.pr import seed_band
from lidar_iris_eval.runs import Run, conventions_lines, load_run
from lidar_iris_eval.runs.schema import result_warnings
from lidar_iris_eval.runs.table import RANKING_COLUMNS, TABLE_COLUMNS, band_rows, cell, table_row

PLOTLY_JS = "plotly.min.js"
#: failure atlas cases per method and kind in a report (``liris report --failures``)
DEFAULT_FAILURES = 3
#: resolution of the embedded failure atlas figures
ATLAS_DPI = 90
INSTALL_HINT = "the HTML report needs plotly: pip install 'lidar_iris_eval[report]'"
#: largest side of an embedded affinity image, in pixels (tiles keep the minimum distance)
MAX_AFFINITY_PX = 600
COLORS = ("#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#F0E442", "#000000")


def _plotly():
    try:
        import plotly
        import plotly.graph_objects as go
    except ImportError:
        raise LirisError("liris report", INSTALL_HINT) from None
    return plotly, go


def build_report(run_dir: str | os.PathLike, out: str | os.PathLike | None = None,
                 overwrite: bool = False, max_affinity_px: int = MAX_AFFINITY_PX,
                 failures: int = DEFAULT_FAILURES) -> Path:
    """Write ``index.html`` and ``plotly.min.js`` for the run in ``run_dir``.

    ``failures``: cases per method and kind in the failure atlas section (0: none).

    ``out`` defaults to ``<run>/report``. An existing report folder is only
    replaced with ``overwrite``. The folder is assembled aside and moved into
    place in one rename, so a reader never sees half a report.
    """
    plotly, go = _plotly()
    run = load_run(run_dir)
    out = Path(out) if out is not None else run.path / "report"
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise LirisError(out, "report folder already exists; pass --overwrite to replace it")
    if overwrite:  # only a report liris wrote, with nothing of the user's in it
        check_replaceable(out, ("report",))
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; a report is meant to be shared
    try:
        try:
            (tmp / PLOTLY_JS).write_text(plotly.offline.get_plotlyjs(), encoding="utf-8")
            (tmp / "index.html").write_text(render_page(run, go, max_affinity_px, failures),
                                            encoding="utf-8")
        except OSError as err:  # name the report, not the folder it was assembled in
            raise os_error(err, out / "index.html", "cannot write the report") from None
        write_manifest(tmp, "report")
        if out.exists() or out.is_symlink():
            if not overwrite:
                raise LirisError(out, "report folder appeared while writing; not replaced")
            check_replaceable(out, ("report",))
        replace_folder(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out / "index.html"


def warnings_list(run: Run) -> str:
    """The warnings stored with the results (a degenerate descriptor...), or nothing."""
    lines = result_warnings(run.rows)
    if not lines:
        return ""
    items = "".join(f"<li>{html.escape(line)}</li>" for line in lines)
    return ("<div class='warnings'><p><b>Warnings that qualify these results</b></p>"
            f"<ul>{items}</ul></div>")


def render_page(run: Run, go, max_affinity_px: int = MAX_AFFINITY_PX,
                failures: int = 0) -> str:
    """The page's HTML text (``failures`` > 0: with the failure atlas section)."""
    sequence = run.config.get("sequence") or run.metrics.get("sequence") or {}
    title = f"liris report: {run.name}"
    version = html.escape(str(run.metrics.get("version")))
    sections = [
        f"<h1>{html.escape(title)}</h1>",
        f"<p class='meta'>sequence {html.escape(str(sequence.get('name')))} "
        f"({sequence.get('n_frames')} frames) &middot; liris {version}"
        f" &middot; created {html.escape(str(run.metrics.get('created')))}</p>",
        "<h2>Metrics</h2>", metrics_table(run), warnings_list(run),
        "<h2>Conventions</h2>", "<ul>" + "".join(
            f"<li>{html.escape(line)}</li>" for line in conventions_lines(run.conventions,
                                                                          run.config)) + "</ul>",
    ]
    if band_rows(run.rows):
        sections += ["<h2>Convention band (protocol 1)</h2>",
                     "<p>Each metric under the run's own convention, and in brackets its "
                     "minimum and maximum over the convention presets that apply to the run "
                     "(one matching pass; the PR figure shades the presets' spread).</p>",
                     band_table(run)]
    for protocol in (1, 2):
        if run.descriptors(protocol):
            sections += [f"<h2>PR curves, protocol {protocol}</h2>",
                         _div(pr_figure(run, protocol, go), f"pr-protocol{protocol}")]
    if run.descriptors("cross-session"):
        sections += ["<h2>PR curves, cross-session (top-1 per query)</h2>",
                     _div(pr_figure(run, "cross-session", go), "pr-cross-session")]
    if any(r.get("recall_at_n") for r in run.rows):
        sections += ["<h2>Recall@N</h2>", "<p>Undefined values (beyond a two-stage method's "
                     "K candidates) are gaps.</p>", _div(recall_figure(run, go), "recall-at-n")]
    if run.descriptors(1) and run.has("positions.npy"):
        sections += ["<h2>Trajectory: protocol 1 at each method's max-F1 threshold</h2>",
                     "<p>Click a legend entry to show or hide it; one method is shown at first."
                     "</p>", _div(trajectory_figure(run, go), "trajectory")]
    if run.loop_tables("loops"):
        sections += ["<h2>Loops of each --loops file</h2>",
                     "<p>Each loop is a segment between its two poses: green true, red false "
                     "(ground-truth distance under / not under the radius), grey dashed not "
                     "scored. The bars are the APE RMSE (after SE(3) alignment) of the pose "
                     "graph optimised with no loops, its true loops and all its loops, and "
                     "what each false loop adds alone (docs/loops.md).</p>",
                     loop_images(run)]
    if run.descriptors(2):
        sections += ["<h2>Affinity matrices (protocol 2)</h2>",
                     "<p>Similarity = 1 &minus; min-max normalised distance (bright = similar);"
                     " tiles show their most similar pair.</p>", affinity_images(run,
                                                                                 max_affinity_px)]
    if failures > 0 and run.descriptors(1):
        sections += ["<h2>Failure atlas (protocol 1)</h2>",
                     f"<p>Per method, the {failures} most confident false positives (lowest "
                     f"descriptor distance) and the {failures} revisit queries missed worst at "
                     "the max-F1 threshold (highest distance): both scans' bird's-eye views at "
                     "the method's and at the ground-truth pose, the method's own "
                     "representation where it is cheap, and the pair on the trajectory.</p>",
                     failure_atlas(run, failures)]
    body = "\n".join(sections)
    return f"""<!DOCTYPE html>
<html lang="en">
<head>
<meta charset="utf-8">
<title>{html.escape(title)}</title>
<script src="{PLOTLY_JS}"></script>
<style>
body {{ font-family: sans-serif; margin: 1.5em auto; max-width: 1100px; color: #222; }}
table {{ border-collapse: collapse; font-size: 0.9em; }}
th, td {{ padding: 0.25em 0.6em; border-bottom: 1px solid #ddd; }}
td.num {{ text-align: right; font-variant-numeric: tabular-nums; }}
.meta {{ color: #666; }}
figure {{ display: inline-block; margin: 0.5em; text-align: center; }}
figure img {{ width: 320px; image-rendering: pixelated; border: 1px solid #ccc; }}
figure.atlas img {{ width: 100%; image-rendering: auto; }}
figure.atlas {{ display: block; }}
</style>
</head>
<body>
{body}
</body>
</html>
"""


def _div(fig, div_id: str) -> str:
    return fig.to_html(full_html=False, include_plotlyjs=False, div_id=div_id,
                       config={"displaylogo": False, "responsive": True})


def metrics_table(run: Run) -> str:
    """The summary table (the same cells as ``liris show``) as HTML."""
    rows = [table_row(r) for r in run.rows]
    columns = [*TABLE_COLUMNS, *[k for k in RANKING_COLUMNS if any(k in r for r in rows)]]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = []
    for r in rows:
        cells = []
        for c in columns:
            value = r.get(c)
            numeric = isinstance(value, (int, float)) and not isinstance(value, bool)
            cls = " class='num'" if numeric else ""
            cells.append(f"<td{cls}>{html.escape(cell(value))}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return (f"<table id='metrics'><thead><tr>{head}</tr></thead>"
            f"<tbody>{''.join(body)}</tbody></table>")


def failure_atlas(run: Run, n: int) -> str:
    """The failure atlas figures as embedded PNGs (a note when the scans are not there)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lidar_iris_eval.plotting.atlas import build_failures
    from lidar_iris_eval.plotting.figures import open_run_sequence

    figures = build_failures(run, n, open_run_sequence)
    if not figures:
        return ("<div id='failure-atlas'><p>Not drawn: the run's scans could not be opened "
                "(see the warning printed).</p></div>")
    parts = []
    for key, fig in figures.items():
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=ATLAS_DPI)
        plt.close(fig)
        data = base64.b64encode(buffer.getvalue()).decode("ascii")
        name = html.escape(key.removeprefix("failures_"))
        parts.append(f"<figure class='atlas'><img alt='failure atlas {name}' "
                     f"src='data:image/png;base64,{data}'><figcaption>{name}</figcaption>"
                     "</figure>")
    return "<div id='failure-atlas'>" + "".join(parts) + "</div>"


def band_table(run: Run) -> str:
    """``--convention-band``: own [min–max] per metric (the cells of ``liris show``)."""
    rows = band_rows(run.rows)
    columns = list(rows[0])
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(cell(r.get(c)))}</td>" for c in columns)
                   + "</tr>" for r in rows)
    return (f"<table id='convention-band'><thead><tr>{head}</tr></thead>"
            f"<tbody>{body}</tbody></table>")


def recall_figure(run: Run, go):
    """Recall@N against N (1..25) of every row with ranking metrics."""
    fig = go.Figure()
    for k, row in enumerate(r for r in run.rows if r.get("recall_at_n")):
        values = [None if v is None else 100 * v for v in row["recall_at_n"]]
        fig.add_trace(go.Scatter(
            x=list(range(1, len(values) + 1)), y=values, mode="lines+markers",
            name=f"{row['descriptor']}/{row.get('preset')} (R@1 {cell(row.get('recall_at_1'))})",
            line={"color": COLORS[k % len(COLORS)]}, connectgaps=False))
    fig.update_layout(xaxis={"title": "N", "range": [0.5, 25.5]},
                      yaxis={"title": "Recall@N [%]", "range": [0, 102]},
                      height=400, margin={"l": 60, "r": 20, "t": 20, "b": 50})
    return fig


def pr_figure(run: Run, protocol: int, go):
    """Precision against recall from each descriptor's ``pr.csv``."""
    fig = go.Figure()
    for k, name in enumerate(run.descriptors(protocol)):
        row = run.row(protocol, name)
        curve = run.pr(protocol, name)
        band = seed_band(run.path / "protocol1" / name, pattern="pr_convention-*.csv") \
            if protocol == 1 else None
        if band is not None:  # --convention-band: the presets' spread, shaded
            grid, low, high, count = band
            fig.add_trace(go.Scatter(
                x=[*grid, *grid[::-1]], y=[*high, *low[::-1]], fill="toself", mode="lines",
                line={"width": 0}, fillcolor=COLORS[k % len(COLORS)], opacity=0.2,
                name=f"{name}: {count} conventions", hoverinfo="skip"))
        fig.add_trace(go.Scatter(
            x=curve["recall"], y=curve["precision"], mode="lines",
            name=f"{name}/{row.get('preset')} (AP {cell(row.get('ap'))})",
            line={"color": COLORS[k % len(COLORS)], "shape": "hv"},
            customdata=curve["threshold"],
            hovertemplate="recall %{x:.4f}<br>precision %{y:.4f}<br>threshold %{customdata:.6g}"))
    fig.update_layout(xaxis={"title": "recall", "range": [0, 1.02]},
                      yaxis={"title": "precision", "range": [0, 1.02]},
                      height=430, margin={"l": 60, "r": 20, "t": 20, "b": 50},
                      legend={"x": 0.01, "y": 0.02, "bgcolor": "rgba(255,255,255,0.7)"})
    return fig


def trajectory_figure(run: Run, go):
    """The path in the ground plane with the protocol 1 outcomes of each descriptor."""
    from lidar_iris_eval.evaluation.ground_truth import ground_plane_axes
    from lidar_iris_eval.plotting.style import OUTCOME_COLORS
    from lidar_iris_eval.plotting.trajectory import OUTCOME_LABELS, outcome_counts, outcomes

    frame = run.conventions.get("pose_frame", "camera")
    a, b = ground_plane_axes(frame if frame in ("camera", "lidar") else "camera")
    xy = np.asarray(run.positions(), dtype=np.float64)[:, [a, b]]
    fig = go.Figure()
    fig.add_trace(go.Scatter(x=xy[:, 0], y=xy[:, 1], mode="lines", name="path",
                               line={"color": "#aaaaaa", "width": 1}, hoverinfo="skip"))
    # the same four outcomes, labels and counts as trajectory.png (plotting/trajectory.py):
    # a wrong match on a revisit query is not a false alarm, so TP + wrong + missed = revisits
    symbols = {"tp": "circle", "wrong": "triangle-up-open", "missed": "circle-open",
               "false_alarm": "x"}
    for k, name in enumerate(run.descriptors(1)):
        row = run.row(1, name)
        threshold = row.get("f1_threshold")
        matches = run.matches(name)
        if threshold is None:
            threshold = -np.inf
        result = outcomes(matches, float(threshold))
        counts = outcome_counts(result)
        for kind, label in OUTCOME_LABELS.items():
            idx = np.asarray(getattr(result, kind), dtype=np.int64)
            fig.add_trace(go.Scatter(
                x=xy[idx, 0], y=xy[idx, 1], mode="markers", legendgroup=name,
                name=f"{name}: {label} ({counts[kind]})",
                visible=True if k == 0 else "legendonly",
                marker={"symbol": symbols[kind], "color": OUTCOME_COLORS[kind],
                        "size": 6 if kind != "tp" else 4},
                text=[f"query {i}" for i in idx], hoverinfo="text"))
    axis = "xyz"
    fig.update_layout(xaxis={"title": f"{axis[a]} (m, {frame} frame)"},
                      yaxis={"title": f"{axis[b]} (m)", "scaleanchor": "x", "scaleratio": 1},
                      height=560, margin={"l": 60, "r": 20, "t": 20, "b": 50})
    return fig


def affinity_png(matrix: np.ndarray, max_px: int = MAX_AFFINITY_PX) -> bytes:
    """A PNG of the similarity image of an ``(N, N)`` distance matrix, at most ``max_px`` wide."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from lidar_iris_eval.plotting.affinity import block_reduce, similarity

    n = matrix.shape[0]
    block = max(1, int(np.ceil(n / max_px)))
    reduced = block_reduce(np.asarray(matrix), block, "min")
    image = similarity(reduced)
    buffer = io.BytesIO()
    plt.imsave(buffer, image, cmap="viridis", vmin=0.0, vmax=1.0, format="png")
    return buffer.getvalue()


def loop_images(run: Run) -> str:
    """The loops-on-trajectory and pose-graph APE figures of a --loops run, as PNG."""
    from lidar_iris_eval.plotting.figures import build_loops

    figures = []
    for fig, caption in zip(build_loops(run), ("loops on the trajectory",
                                               "pose-graph APE RMSE"), strict=True):
        if fig is None:
            continue
        buffer = io.BytesIO()
        fig.savefig(buffer, format="png", dpi=110)
        data = base64.b64encode(buffer.getvalue()).decode("ascii")
        figures.append(f"<figure><img style='width: 640px' alt='{caption}' "
                       f"src='data:image/png;base64,{data}'><figcaption>{caption}"
                       f"</figcaption></figure>")
    return "<div id='loops'>" + "".join(figures) + "</div>"


def affinity_images(run: Run, max_px: int = MAX_AFFINITY_PX) -> str:
    figures = []
    for name in run.descriptors(2):
        row = run.row(2, name)
        found = run.affinity_for_figures(name)  # above 8192 frames: every k-th frame
        if found is None:
            continue
        matrix, step = found
        data = base64.b64encode(affinity_png(matrix, max_px)).decode("ascii")
        decimated = f" (decimated by {step})" if step > 1 else ""
        caption = html.escape(f"{name}/{row.get('preset')}{decimated}")
        figures.append(f"<figure><img alt='affinity {caption}' src='data:image/png;base64,"
                       f"{data}'><figcaption>{caption}</figcaption></figure>")
    return "<div id='affinity'>" + "".join(figures) + "</div>"
