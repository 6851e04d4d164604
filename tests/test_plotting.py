"""``liris plot``: every figure is written at its fixed size and draws the run's data.

The run directories here are fakes in the results format (docs/results-format.md)
built by :func:`make_run`: a trajectory that drives a 60-frame circle one and
a half times, so frames 60–89 revisit frames 0–29, with descriptor distances
that grow with the true distance plus noise. PR curves, matches and metrics are
computed in this file with plain loops, independently of ``liris eval``.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from conftest import run_cli, write_kitti_sequence

from lidar_iris_eval.errors import LirisError, LirisWarning
from lidar_iris_eval.plotting import (
    build_affinity,
    build_iris,
    build_pr,
    build_pr_compare,
    build_timing,
    build_trajectory,
    load_run,
    plot_compare,
    plot_run,
)
from lidar_iris_eval.plotting.affinity import block_reduce, similarity
from lidar_iris_eval.plotting.iris_figures import feature_panels, iris_alignment_figure
from lidar_iris_eval.plotting.pr import thin_indices
from lidar_iris_eval.plotting.trajectory import outcomes

N_FRAMES = 90
EXCLUDE = 30
RADIUS = 4.0
METHODS = {"lidar-iris": 0.02, "m2dp": 0.08}  # name -> noise on the distance


# ---- the fake run -----------------------------------------------------------------------
def exact_pr(scores: np.ndarray, accepted_ok: np.ndarray, n_positive: int) -> pd.DataFrame:
    """Precision and recall at every distinct threshold, by brute force."""
    rows = []
    for tau in np.unique(scores):
        accepted = scores <= tau
        tp = int(np.sum(accepted & accepted_ok))
        rows.append((tau, tp / int(accepted.sum()), tp / n_positive))
    return pd.DataFrame(rows, columns=["threshold", "precision", "recall"])


def summary(pr: pd.DataFrame) -> dict:
    p, r = pr["precision"].to_numpy(), pr["recall"].to_numpy()
    f1 = np.where(p + r > 0, 2 * p * r / np.maximum(p + r, 1e-300), 0)
    best = int(np.argmax(f1))
    ap = float(np.sum(np.diff(np.concatenate([[0.0], r])) * p))
    return {"ap": ap, "f1_max": float(f1[best]), "f1_threshold": float(pr["threshold"][best])}


def circle_positions(noise: float, rng) -> np.ndarray:
    """Camera-frame positions (ground plane x–z) on a 60-frame circle of radius 15 m."""
    angle = 2 * np.pi * np.arange(N_FRAMES) / 60
    positions = np.stack([15 * np.cos(angle), np.zeros(N_FRAMES), 15 * np.sin(angle)], axis=1)
    return positions + rng.normal(0, noise, positions.shape) * [1, 0, 1]


def make_run(root: Path, seed: int = 0, sequence: str = "/nonexistent/sequence",
             noise: float = 0.3) -> Path:
    rng = np.random.default_rng(seed)
    positions = circle_positions(noise, rng)
    gap = np.linalg.norm(positions[:, None] - positions[None], axis=2)
    positive = (gap < RADIUS) & ~np.eye(N_FRAMES, dtype=bool)
    root.mkdir(parents=True)
    np.save(root / "positions.npy", positions)
    poses = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    poses[:, :3, 3] = positions
    np.save(root / "poses.npy", poses)
    results = []
    for name, noise in METHODS.items():
        d = gap / 30 + rng.normal(0, noise, gap.shape)
        d = ((d + d.T) / 2).astype(np.float32)
        np.fill_diagonal(d, np.nan)
        # protocol 1: best match among j <= i - E
        rows = []
        for i in range(EXCLUDE, N_FRAMES):
            j = int(np.argmin(d[i, : i - EXCLUDE + 1]))
            rows.append((i, j, float(d[i, j]), float("nan"), gap[i, j],
                         bool(positive[i, : i - EXCLUDE + 1].any()), bool(positive[i, j])))
        matches = pd.DataFrame(rows, columns=["query", "match", "distance", "yaw_deg",
                                              "match_dist_m", "is_revisit", "is_true"])
        pr1 = exact_pr(matches["distance"].to_numpy(), matches["is_true"].to_numpy(),
                       int(matches["is_revisit"].sum()))
        off = ~np.eye(N_FRAMES, dtype=bool)
        pr2 = exact_pr(d[off].astype(np.float64), positive[off], int(positive.sum()))
        for protocol, pr in ((1, pr1), (2, pr2)):
            folder = root / f"protocol{protocol}" / name
            folder.mkdir(parents=True)
            pr.to_csv(folder / "pr.csv", index=False)
            row = {"protocol": protocol, "descriptor": name, "preset": "paper", **summary(pr),
                   "extract_ms_per_scan": 5.0}
            if protocol == 1:
                matches.to_csv(folder / "matches.csv", index=False)
                row["match_ms_per_query"] = 0.5 if name == "m2dp" else 40.0
            else:
                np.save(folder / "affinity.npy", d)
                row["match_us_per_pair"] = 3.0 if name == "m2dp" else 250.0
            results.append(row)
        (root / "timing").mkdir(exist_ok=True)
        times = rng.lognormal(np.log(0.004 if name == "m2dp" else 0.012), 0.2, N_FRAMES)
        pd.DataFrame({"scan": np.arange(N_FRAMES), "extract_s": times}).to_csv(
            root / "timing" / f"{name}.csv", index=False)
    (root / "metrics.json").write_text(json.dumps({"version": "test", "results": results}))
    config = {"version": "test", "sequence": {"path": sequence},
              "descriptors": {n: {"preset": "paper", "params": {}} for n in METHODS},
              "protocols": [1, 2], "radius": RADIUS,
              "exclude": {"value": EXCLUDE, "preset": "paper"}, "distance": "3d",
              "pose_frame": "camera", "recall_denominator": "revisits", "candidates": None}
    (root / "config.yaml").write_text(yaml.safe_dump(config))
    return root


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    return make_run(tmp_path_factory.mktemp("results") / "run-a")


def png_size(path: Path) -> tuple[int, int]:
    """Width and height from the PNG header (IHDR), without any image library."""
    with open(path, "rb") as f:
        head = f.read(24)
    assert head[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", head[16:24])


def line(fig, gid: str):
    found = [ln for ax in fig.axes for ln in ax.get_lines() if ln.get_gid() == gid]
    assert len(found) == 1, f"expected one line {gid!r}, found {len(found)}"
    return found[0]


def image(fig, gid: str):
    found = [im for ax in fig.axes for im in ax.get_images() if im.get_gid() == gid]
    assert len(found) == 1, gid
    return found[0]


# ---- all figures, files and sizes ----------------------------------------------------------
def test_plot_writes_every_figure_at_fixed_size(run_dir, tmp_path, capsys):
    out = tmp_path / "figs"
    code, stdout, stderr = run_cli(["plot", str(run_dir), "--out", str(out)], capsys)
    assert code == 0, stderr
    written = [Path(p) for p in stdout.split()]
    stems = ["affinity", "pr_protocol1", "pr_protocol2", "timing", "trajectory"]
    # every figure twice: the PNG asked for and a vector PDF for papers
    assert sorted(p.name for p in written) == sorted(f"{s}.{x}" for s in stems
                                                     for x in ("png", "pdf"))
    assert all((out / f"{s}.pdf").read_bytes()[:5] == b"%PDF-" for s in stems)
    assert "sequence not found" in stderr  # iris figures need the scans: skipped, said so
    for path in written:
        assert path.parent == out and path.stat().st_size > 10_000
    # 300 dpi. PR: curves reach recall 0.9, so two 3.5 × 2.6 in panels (full, zoom) plus
    # 0.13 in per legend row (3 entries in 3 columns: 1 row) + 0.1 in; timing 3.5 × 2.2 in;
    # affinity one row of up to five panels, 7 in wide, 1.62 in + 0.55 in for the two colour
    # bars; trajectory two panels 1.85 + 0.42 in
    assert png_size(out / "pr_protocol1.png") == (2100, round((2.6 + 0.13 + 0.1) * 300))
    assert png_size(out / "timing.png") == (1050, 660)
    assert png_size(out / "affinity.png") == (2100, round((1.62 + 0.55) * 300))
    assert png_size(out / "trajectory.png") == (1050, round((1.85 + 0.42) * 300))


def test_default_output_is_the_runs_figures_folder_in_vector_format(run_dir):
    with pytest.warns(LirisWarning):
        written = plot_run(run_dir, fmt="pdf")
    assert {p.parent for p in written} == {run_dir / "figures"}
    assert all(p.suffix == ".pdf" and p.read_bytes()[:5] == b"%PDF-" for p in written)


# ---- PR curves ------------------------------------------------------------------------------
@pytest.mark.parametrize("protocol", [1, 2])
def test_pr_curves_plot_exactly_pr_csv(run_dir, protocol):
    run = load_run(run_dir)
    fig = build_pr(run, protocol)
    metrics = json.loads((run_dir / "metrics.json").read_text())["results"]
    for name in METHODS:
        table = pd.read_csv(run_dir / f"protocol{protocol}" / name / "pr.csv")
        curve = line(fig, f"pr:{name}")
        np.testing.assert_array_equal(curve.get_xdata(), table["recall"].to_numpy())
        np.testing.assert_array_equal(curve.get_ydata(), table["precision"].to_numpy())
        # marker at the point of maximum F1 = 2PR/(P+R)
        p, r = table["precision"].to_numpy(), table["recall"].to_numpy()
        best = max(range(len(p)), key=lambda k: 2 * p[k] * r[k] / (p[k] + r[k]))
        marker = line(fig, f"f1max:{name}")
        assert (marker.get_xdata()[0], marker.get_ydata()[0]) == (r[best], p[best])
        row = next(m for m in metrics if m["protocol"] == protocol and m["descriptor"] == name)
        assert f"AP {row['ap']:.3f}" in curve.get_label()
        assert f"F1max {row['f1_max']:.3f}" in curve.get_label()
    ax = fig.axes[0]
    assert ax.get_xlabel() == "Recall" and ax.get_ylabel() == "Precision"
    assert ax.get_legend() is None  # never on the data: below the axes
    legend = [t.get_text() for t in fig.legends[0].get_texts()]
    assert len(legend) == len(METHODS) + 1 and legend[-1] == "max F1"
    # colours are fixed per method, whatever the run
    assert line(fig, "pr:lidar-iris").get_color() != line(fig, "pr:m2dp").get_color()


def _overlaps(fig, artist) -> list:
    """Axes whose drawing area ``artist``'s box intersects, after a draw."""
    fig.canvas.draw()
    box = artist.get_window_extent()
    return [ax for ax in fig.axes if ax.get_window_extent().overlaps(box)]


def test_legend_is_outside_the_data_and_a_zoom_shows_high_recall():
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from lidar_iris_eval.plotting.pr import ZOOM_RECALL, PRCurve, pr_figure

    r = np.linspace(0, 1, 101)
    curves = [PRCurve("a", "A (AP 0.99)", "#D55E00", r, np.where(r < 0.95, 1.0, 0.8)),
              PRCurve("b", "B (AP 0.98)", "#0072B2", r, np.where(r < 0.93, 1.0, 0.7)),
              PRCurve("c", "C (AP 0.10)", "#009E73", r[:40], np.linspace(1, 0.2, 40))]
    fig = pr_figure(curves, "title")
    FigureCanvasAgg(fig)
    main, zoom = fig.axes[:2]
    assert not _overlaps(fig, fig.legends[0])  # no axes (hence no curve) under the legend
    assert zoom.get_xlim()[0] == pytest.approx(ZOOM_RECALL - 0.005)
    assert zoom.get_ylim()[0] < 0.7 < zoom.get_ylim()[1]  # the lowest point there is shown
    for c in curves[:2]:
        np.testing.assert_array_equal(line(fig, f"zoom:pr:{c.key}").get_ydata(), c.precision)
    # a run where nothing reaches recall 0.9 gets no zoom panel
    assert len(pr_figure(curves[2:]).axes) == 1


def test_long_curves_are_thinned_without_losing_shape():
    t = np.linspace(0, 1, 200_001)
    recall, precision = t, 1 - t**4 + 0.001 * np.sin(500 * t)
    keep = thin_indices(recall, precision, step=1e-3, keep=[123_457])
    assert keep[0] == 0 and keep[-1] == len(t) - 1 and 123_457 in keep
    assert len(keep) < 10_000
    assert np.all(np.diff(keep) > 0)
    # every dropped point lies within one step of a kept point along the curve
    arc = np.concatenate([[0], np.cumsum(np.hypot(np.diff(recall), np.diff(precision)))])
    gaps = np.diff(arc[keep])
    assert gaps.max() <= 1e-3 + np.hypot(np.diff(recall), np.diff(precision)).max()


def test_compare_labels_runs_and_overlays_their_curves(run_dir, tmp_path):
    other = make_run(tmp_path / "run-b", seed=1)
    runs = [load_run(run_dir), load_run(other)]
    fig = build_pr_compare(runs, 1)
    for run in runs:
        for name in METHODS:
            curve = line(fig, f"pr:{run.name}: {name}")
            assert curve.get_label().startswith(f"{run.name}: ")
            table = pd.read_csv(run.path / "protocol1" / name / "pr.csv")
            np.testing.assert_array_equal(curve.get_ydata(), table["precision"].to_numpy())
    dashes = {line(fig, f"pr:{run.name}: m2dp").get_linestyle() for run in runs}
    assert len(dashes) == 2
    written = plot_compare([run_dir, other], tmp_path / "cmp", "png")
    assert sorted(p.name for p in written) == ["pr_protocol1.pdf", "pr_protocol1.png",
                                               "pr_protocol2.pdf", "pr_protocol2.png"]
    with pytest.warns(LirisWarning, match="replacing existing figure"):  # --out: never silent
        plot_compare([run_dir, other], tmp_path / "cmp", "png")
    # full and zoom panels; legend below them: 2.6 in + 0.13 in per row (4 curves + max F1
    # in 3 columns: 2 rows) + 0.1 in
    assert png_size(tmp_path / "cmp" / "pr_protocol1.png") == (2100, round(2.96 * 300))


# ---- affinity -----------------------------------------------------------------------------
def test_block_reduce_and_similarity_by_hand():
    m = np.array([[np.nan, 1, 5, 6],
                  [2, np.nan, 7, 3],
                  [9, 8, np.nan, 4],
                  [0.5, 8, 4, np.nan]])
    np.testing.assert_array_equal(block_reduce(m, 2, "min"), [[1, 3], [0.5, 4]])
    np.testing.assert_array_equal(block_reduce(m[:3, :3], 2, "max"), [[2, 7], [9, np.nan]])
    d = np.array([[np.nan, 0.2, 0.6], [0.2, np.nan, 1.0], [0.6, 1.0, np.nan]])
    np.testing.assert_allclose(similarity(d), [[1, 1, 0.5], [1, 1, 0], [0.5, 0, 1]])


def test_affinity_shows_ground_truth_and_methods_on_one_scale(run_dir):
    run = load_run(run_dir)
    fig = build_affinity(run)
    positions = np.load(run_dir / "positions.npy")
    gap = np.linalg.norm(positions[:, None] - positions[None], axis=2)
    expected_gt = (gap < RADIUS).astype(float)  # includes the diagonal (distance 0)
    np.testing.assert_array_equal(image(fig, "affinity:ground-truth").get_array(), expected_gt)
    d = np.load(run_dir / "protocol2" / "m2dp" / "affinity.npy").astype(np.float64)
    off = d[~np.isnan(d)]
    expected = 1 - (d - off.min()) / (off.max() - off.min())
    np.fill_diagonal(expected, 1.0)
    np.testing.assert_allclose(image(fig, "affinity:m2dp").get_array(), expected, atol=1e-12)
    images = [im for ax in fig.axes for im in ax.get_images()]
    assert len(images) == 1 + len(METHODS)
    assert {im.get_clim() for im in images} == {(0.0, 1.0)}
    # two colour bars: binary ground truth apart from the per-method similarity
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    labels = sorted(ax.get_xlabel() for ax in bars)  # horizontal bars under the panels
    assert len(bars) == 2 and labels[0].startswith("ground truth") and f"{RADIUS:g} m" in labels[0]
    assert "per method" in labels[1] and "d_min" in labels[1]
    assert image(fig, "affinity:ground-truth").get_cmap().name != \
        image(fig, "affinity:m2dp").get_cmap().name
    titles = [ax.get_title() for ax in fig.axes if ax.get_images()]
    assert any(t.startswith("M2DP\nd ∈ [") for t in titles)  # the range normalised


def decimate_run(run_dir: Path, root: Path, step: int, note_step: int | None = None) -> Path:
    """A copy of ``run_dir`` as a run above 8192 frames writes it: no affinity.npy, only
    ``affinity_decimated.npy`` (frames 0, step, 2·step, … in float16, NaN diagonal)."""
    import shutil

    out = root / f"decimated-{step}-{note_step}"
    shutil.copytree(run_dir, out)
    metrics = json.loads((out / "metrics.json").read_text())
    for row in metrics["results"]:
        if row["protocol"] != 2:
            continue
        folder = out / "protocol2" / row["descriptor"]
        full = np.load(folder / "affinity.npy")
        (folder / "affinity.npy").unlink()
        np.save(folder / "affinity_decimated.npy", full[::step, ::step].astype(np.float16))
        side = -(-N_FRAMES // step)
        row["affinity_stored"] = (f"decimated float16 for figures: every {note_step or step}th "
                                  f"frame ({side} x {side}); metrics use every pair")
    (out / "metrics.json").write_text(json.dumps(metrics))
    return out


def test_affinity_above_8192_frames_is_drawn_from_the_decimated_matrix(run_dir, tmp_path):
    step = 3
    run = load_run(decimate_run(run_dir, tmp_path, step))
    fig = build_affinity(run)
    assert fig is not None
    positions = np.load(run_dir / "positions.npy")[::step]  # frames 0, 3, ..., 87
    gap = np.linalg.norm(positions[:, None] - positions[None], axis=2)
    np.testing.assert_array_equal(image(fig, "affinity:ground-truth").get_array(),
                                  (gap < RADIUS).astype(float))
    for name in METHODS:
        d = np.load(run_dir / "protocol2" / name / "affinity.npy")[::step, ::step]
        d = d.astype(np.float16).astype(np.float64)  # what the decimated file holds
        off = d[~np.isnan(d)]
        expected = 1 - (d - off.min()) / (off.max() - off.min())
        np.fill_diagonal(expected, 1.0)
        drawn = image(fig, f"affinity:{name}")
        assert drawn.get_array().shape == (30, 30)
        np.testing.assert_allclose(drawn.get_array(), expected, atol=1e-12)
        # axes in frames of the run: cell i is frame 3i
        assert drawn.get_extent() == [-1.5, 88.5, 88.5, -1.5]
    assert fig._suptitle.get_text().startswith("decimated by 3: frames 0, 3, 6, … (30 of 90")
    with pytest.warns(LirisWarning, match="sequence not found"):  # no scans: no iris figures
        written = plot_run(run.path, tmp_path / "figs", "png")
    assert (tmp_path / "figs" / "affinity.png") in written


def test_decimated_affinity_whose_step_disagrees_is_a_one_line_error(run_dir, tmp_path, capsys):
    bad = decimate_run(run_dir, tmp_path, 3, note_step=4)  # 30 x 30 stored, note says 4
    code, _, err = run_cli(["plot", str(bad), "--out", str(tmp_path / "figs")], capsys)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1, err
    assert "affinity_decimated.npy: decimated affinity has shape (30, 30), expected (23, 23)" \
        in lines[0]


def test_liris_eval_decimated_run_gets_its_affinity_figure(tmp_path, capsys, monkeypatch):
    """End to end: force decimation with small limits, then plot what eval wrote."""
    from test_protocols import two_pass_sequence

    from lidar_iris_eval.descriptors import _REGISTRY
    from lidar_iris_eval.evaluation import streaming_pr

    monkeypatch.setitem(_REGISTRY, "toy", "test_protocols:ToyHist")
    monkeypatch.setattr(streaming_pr, "AUTO_FLOAT32_MAX_FRAMES", 4)
    monkeypatch.setattr(streaming_pr, "AUTO_FLOAT16_MAX_FRAMES", 8)
    monkeypatch.setattr(streaming_pr, "DECIMATED_SIDE", 10)  # 24 frames: step 3, 8 x 8
    seq = two_pass_sequence(tmp_path / "seq", n_per_pass=12)
    out = tmp_path / "run"
    code, _, err = run_cli(["eval", seq, "--protocol", "2", "-d", "toy", "--out", out,
                            "--cache-dir", tmp_path / "cache", "-q"], capsys)
    assert code == 0, err
    folder = out / "protocol2" / "toy"
    assert not (folder / "affinity.npy").exists()
    stored = np.load(folder / "affinity_decimated.npy")
    assert stored.shape == (8, 8)
    fig = build_affinity(load_run(out))
    assert "decimated by 3" in fig._suptitle.get_text()
    # the passes are 12 frames apart: frames 0, 3, ..., 21 pair up as (k, k + 12) = cells
    # (i, i + 4), the only positives, at 0 m
    expected_gt = np.eye(8)
    expected_gt[np.arange(4), np.arange(4, 8)] = expected_gt[np.arange(4, 8), np.arange(4)] = 1
    np.testing.assert_array_equal(image(fig, "affinity:ground-truth").get_array(), expected_gt)
    d = stored.astype(np.float64)
    assert np.all(d[np.arange(4), np.arange(4, 8)] == 0)  # byte-identical scans
    drawn = image(fig, "affinity:toy").get_array()
    np.testing.assert_allclose(drawn[np.arange(4), np.arange(4, 8)], 1.0)
    off = d[~np.isnan(d)]
    expected = 1 - (d - off.min()) / (off.max() - off.min())
    np.fill_diagonal(expected, 1.0)
    np.testing.assert_allclose(drawn, expected, atol=1e-12)
    # the HTML report shows it too, captioned the same way
    from lidar_iris_eval.report_html.page import affinity_images

    section = affinity_images(load_run(out))
    assert section.count("<img") == 1
    assert "<figcaption>toy/default (decimated by 3)</figcaption>" in section


# ---- trajectory -----------------------------------------------------------------------------
def test_outcomes_by_hand():
    matches = pd.DataFrame({
        "query": [30, 31, 32, 33, 34],
        "match": [0, 1, 9, 3, 4],
        "distance": [0.1, 0.3, 0.2, 0.5, 0.25],
        "is_revisit": ["True", "True", "True", "False", "True"],
        "is_true": [True, True, False, False, True],
    })
    got = outcomes(matches, 0.25)
    assert got.tp.tolist() == [30, 34]  # accepted (≤ τ, equality included) and right
    assert got.wrong.tolist() == [32]  # accepted, wrong place, on a revisit
    assert got.false_alarm.tolist() == [] and got.fp.tolist() == [32]
    assert got.missed.tolist() == [31]  # a revisit whose best match was rejected
    assert got.n_revisits == 4 == len(got.tp) + len(got.wrong) + len(got.missed)
    alarm = outcomes(matches.assign(distance=[0.1, 0.3, 0.2, 0.1, 0.25]), 0.25)
    assert alarm.false_alarm.tolist() == [33] and alarm.fp.tolist() == [32, 33]


def test_trajectory_marks_detections_in_the_ground_plane(run_dir):
    run = load_run(run_dir)
    fig = build_trajectory(run)
    positions = np.load(run_dir / "positions.npy")
    path = [ln for ax in fig.axes for ln in ax.get_lines() if ln.get_gid() == "path"][0]
    np.testing.assert_array_equal(path.get_xdata(), positions[:, 0])  # camera frame: x–z
    np.testing.assert_array_equal(path.get_ydata(), positions[:, 2])
    metrics = json.loads((run_dir / "metrics.json").read_text())["results"]
    for name in METHODS:
        tau = next(m["f1_threshold"] for m in metrics
                   if m["protocol"] == 1 and m["descriptor"] == name)
        matches = pd.read_csv(run_dir / "protocol1" / name / "matches.csv")
        tp = matches[(matches["distance"] <= tau) & matches["is_true"]]["query"].to_numpy()
        np.testing.assert_array_equal(line(fig, f"tp:{name}").get_xdata(), positions[tp, 0])
        # every revisit query is shown as exactly one of TP, wrong match, missed
        revisit = matches["is_revisit"].astype(bool)
        wrong = matches[(matches["distance"] <= tau) & ~matches["is_true"] & revisit]
        np.testing.assert_array_equal(line(fig, f"wrong:{name}").get_xdata(),
                                      positions[wrong["query"].to_numpy(), 0])
        shown = sum(len(line(fig, f"{k}:{name}").get_xdata()) for k in ("tp", "wrong", "missed"))
        assert shown == int(revisit.sum())
        title = next(ax.get_title() for ax in fig.axes
                     if any(ln.get_gid() == f"tp:{name}" for ln in ax.get_lines()))
        assert f"of {int(revisit.sum())} revisits" in title
    axes = [ax for ax in fig.axes if ax.get_lines()]
    assert axes[0].get_xlabel() == "x [m] (camera)"
    assert axes[0].get_ylabel() == "z [m] (camera)"


# ---- timing --------------------------------------------------------------------------------
def test_timing_shows_per_scan_spread_and_matching_cost(run_dir):
    fig = build_timing(load_run(run_dir))
    left, right = fig.axes
    for name in METHODS:
        times = pd.read_csv(run_dir / "timing" / f"{name}.csv")["extract_s"].to_numpy()
        median = line(fig, f"median:{name}").get_ydata()
        np.testing.assert_allclose(median, 1e3 * np.median(times))
    heights = {p.get_gid(): p.get_height() for p in right.patches}
    assert heights == {"match:lidar-iris": 250.0, "match:m2dp": 3.0}
    assert right.get_yscale() == "log"  # 250 vs 3 µs: more than 10×
    assert "µs / pair" in right.get_ylabel()


# ---- LiDAR Iris figures ----------------------------------------------------------------------
def test_alignment_rolls_candidate_back_onto_query():
    rng = np.random.default_rng(3)
    query = rng.integers(0, 256, (80, 360), dtype=np.uint8)
    candidate = np.roll(query, 40, axis=1)  # the scan turned 40° CCW
    fig = iris_alignment_figure(query, candidate, yaw_deg=40.0, distance=0.0, frames=(5, 1))
    np.testing.assert_array_equal(image(fig, "iris:aligned").get_array(), query)
    fig = iris_alignment_figure(query, np.roll(query, -15, axis=1), 345.0, 0.0)
    np.testing.assert_array_equal(image(fig, "iris:aligned").get_array(), query)


def test_feature_panels_split_maps_and_grey_out_masked_bits():
    features = np.zeros((8 * 2, 5), dtype=bool)
    features[2, 1] = True  # map 1 (rows 2–3), row 0
    mask = np.zeros_like(features)
    mask[15, 4] = True  # map 7, row 1
    panels = feature_panels(features, mask, n_rows=2)
    assert len(panels) == 8
    assert panels[1][0, 1] == 1.0 and panels[1].sum() == 1.0
    assert panels[7][1, 4] == 0.5


def rotate_z(points: np.ndarray, degrees: float) -> np.ndarray:
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    return points @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T


@pytest.fixture(scope="module")
def run_with_scans(tmp_path_factory) -> tuple[Path, list[np.ndarray]]:
    """A fake run whose config points at real scans on disk.

    Frame 60 returns exactly to frame 0's position (no position noise) with
    the sensor turned, so its scan is frame 0's scan rotated by -40 degrees:
    frame 0 is frame 60 turned +40 degrees (counter-clockwise).
    """
    pytest.importorskip("lidar_iris_eval.descriptors.lidar_iris")
    root = tmp_path_factory.mktemp("withscans")
    rng = np.random.default_rng(5)
    boxes = [rng.uniform(-0.5, 0.5, (150, 3)) * rng.uniform(1, 5, 3)
             + [*rng.uniform(-40, 40, 2), 0.5] for _ in range(40)]
    world = np.concatenate(boxes)
    angles = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    ground = np.stack([np.cos(angles) * 10, np.sin(angles) * 10, np.full(720, -1.7)], axis=1)
    base = np.concatenate([world, ground]).astype(np.float32)
    scans = []
    for i in range(N_FRAMES):
        turn = -40.0 if i == 60 else float(rng.uniform(0, 360)) if i != 0 else 0.0
        pts = rotate_z(base, turn) if i in (0, 60) else rotate_z(base[rng.random(len(base)) < 0.8],
                                                                   turn)
        scans.append(np.column_stack([pts, np.zeros(len(pts))]).astype(np.float32))
    poses = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    poses[:, :3, 3] = circle_positions(0.0, rng)
    seq = write_kitti_sequence(root / "seq", scans, poses)
    return make_run(root / "run", sequence=str(seq), noise=0.0), scans


def test_iris_figures_from_the_runs_sequence(run_with_scans, tmp_path):
    run_dir, scans = run_with_scans
    written = plot_run(run_dir, tmp_path, "png")
    assert {p.name for p in written} >= {"iris_frame.png", "iris_alignment.png"}
    assert png_size(tmp_path / "iris_frame.png") == (1050, 990)  # 3.5 × 3.3 in
    assert png_size(tmp_path / "iris_alignment.png") == (1050, 780)  # 3.5 × 2.6 in
    # default frame: a revisit query whose LiDAR Iris protocol 1 match is a true
    # loop, shown against that match (not the first revisit, which may sit at a junction)
    frame_fig, align_fig = build_iris(load_run(run_dir))
    matches = pd.read_csv(run_dir / "protocol1" / "lidar-iris" / "matches.csv")
    title = frame_fig.axes[0].get_title()
    frame = int(title.rsplit("scan ", 1)[1])  # scans are named 000000.bin...: id = index here
    row = matches[matches["query"] == frame].iloc[0]
    assert bool(row["is_true"]) and bool(row["is_revisit"])
    assert f"scan {int(row['match']):06d}" in align_fig.axes[1].get_title()
    for fig in (frame_fig, align_fig):  # the codes have a colour bar
        bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
        assert len(bars) == 1 and "code" in bars[0].get_ylabel()
    features = [im for ax in frame_fig.axes for im in ax.get_images()
                if str(im.get_gid()).startswith("feature:")]
    assert len(features) == 8  # 4 scales × real/imaginary


def test_alignment_figure_rolls_a_turned_revisit_into_place(run_with_scans):
    run_dir, _ = run_with_scans
    _, fig = build_iris(load_run(run_dir), frame=60)
    query = image(fig, "iris:query").get_array()
    aligned = image(fig, "iris:aligned").get_array()
    assert "scan 000000" in fig.axes[1].get_title()  # the partner is the exact revisit
    assert "yaw 40°" in fig.axes[2].get_title()
    assert np.mean(query == aligned) > 0.99
    assert np.mean(query == image(fig, "iris:candidate").get_array()) < 0.99


# ---- bad input -------------------------------------------------------------------------------
@pytest.mark.parametrize("case", ["missing", "no-metrics", "a-file"])
def test_not_a_results_dir_is_a_one_line_error(tmp_path, capsys, case):
    target = tmp_path / case
    if case == "no-metrics":
        target.mkdir()
    elif case == "a-file":
        target.write_text("x")
    code, _, err = run_cli(["plot", str(target)], capsys)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err
    assert lines[0].startswith("liris: error: ") and str(target) in lines[0]


def test_cli_options_are_checked(run_dir, tmp_path, capsys):
    code, _, err = run_cli(["plot", str(run_dir), "--format", "gif"], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    code, _, err = run_cli(["plot", str(run_dir), str(run_dir)], capsys)
    assert code == 2 and "--compare" in err
    code, _, err = run_cli(["plot", str(run_dir), "--frame", "999", "--out", str(tmp_path)], capsys)
    assert code == 2 and "--frame 999" in err
    with pytest.raises(LirisError, match="at least two"):
        plot_compare([run_dir], tmp_path)


def test_plots_a_real_liris_eval_run(run_with_scans, tmp_path, capsys):
    """The contract end to end: whatever `liris eval` writes, `liris plot` draws."""
    pytest.importorskip("lidar_iris_eval.cli.eval_cmd")
    run_dir, _ = run_with_scans
    seq = load_run(run_dir).sequence_path
    out = tmp_path / "eval"
    code, _, err = run_cli(["eval", str(seq), "--protocol", "1", "--protocol", "2", "--descriptor",
                        "lidar-iris", "--out", str(out), "--cache-dir",
                        str(tmp_path / "cache"), "--quiet"], capsys)
    assert code == 0, err
    written = plot_run(out, fmt="png")
    assert sorted(p.name for p in written) == sorted(
        f"{s}.{x}" for s in ("pr_protocol1", "pr_protocol2", "affinity", "trajectory", "timing",
                             "iris_frame", "iris_alignment") for x in ("png", "pdf"))
    run = load_run(out)
    for protocol in (1, 2):
        fig = build_pr(run, protocol)
        table = pd.read_csv(out / f"protocol{protocol}" / "lidar-iris" / "pr.csv")
        curve = line(fig, "pr:lidar-iris")
        np.testing.assert_array_equal(curve.get_xdata(), table["recall"].to_numpy())
        np.testing.assert_array_equal(curve.get_ydata(), table["precision"].to_numpy())
