"""Affinity matrices: ground truth beside each method (the paper's Fig. 7).

Descriptor distances live on different scales (Iris Hamming in [0, 1], ESF L1
in [0, 2], …), so each method is shown as a *similarity*
``1 − (d − d_min) / (d_max − d_min)`` with ``d_min``, ``d_max`` taken per
method over its off-diagonal pairs: the colours compare pairs *within* a
panel, not methods. Each method panel's title gives its ``[d_min, d_max]``.
Ground truth is binary (positive pair: closer than the radius) and has its
own two-colour bar, separate from the similarity bar, so the two are never
read on one scale. The diagonal (a frame against itself, stored as NaN) is
drawn as 1 in every panel.

Matrices larger than the panel's pixels are reduced in blocks before drawing:
distances by their block *minimum* and ground truth by its block maximum, so
the one-frame-wide loop-closure diagonals that the figure is about cannot be
averaged away by image resampling.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from lidar_iris_eval.plotting import style

#: at most this many matrix cells per panel side (a panel is ~300 px wide at 300 dpi)
MAX_DISPLAY = 600
CMAP = "viridis"
#: ground truth: two greys, deliberately not on the similarity scale
GT_CMAP = ListedColormap(["#F2F2F2", "#222222"], name="liris-gt")
PANEL_HEIGHT = 1.62  # inches per row: a ~1.2 in square panel, its two-line title, ticks
BARS_HEIGHT = 0.55  # the two colour bars under the panels, with their labels
MAX_COLUMNS = 5


def block_reduce(matrix: np.ndarray, block: int, how: str) -> np.ndarray:
    """Reduce an (N, N) matrix over ``block``×``block`` tiles (``min`` or ``max``).

    NaNs are ignored; a tile with no finite value stays NaN. The last tiles
    may be partial (the matrix is padded, not cropped).
    """
    matrix = np.asarray(matrix)
    if block <= 1:
        return matrix.astype(np.float64)
    n = matrix.shape[0]
    size = math.ceil(n / block) * block
    fill = np.inf if how == "min" else -np.inf
    # float32 is exact for the stored distances and halves the memory at KITTI scale
    padded = np.full((size, size), fill, dtype=np.result_type(matrix.dtype, np.float32))
    padded[:n, :n] = np.where(np.isnan(matrix), fill, matrix)
    tiles = padded.reshape(size // block, block, size // block, block)
    out = tiles.min(axis=(1, 3)) if how == "min" else tiles.max(axis=(1, 3))
    out = out.astype(np.float64)
    out[~np.isfinite(out)] = np.nan
    return out


def similarity(distances: np.ndarray) -> np.ndarray:
    """``1 − min-max normalised distance``; the diagonal becomes 1.

    Min and max are taken over finite off-diagonal entries; a constant matrix
    maps to all ones.
    """
    d = np.array(distances, dtype=np.float64)
    n = min(d.shape)
    diag = np.arange(n)
    off = d.copy()
    off[diag, diag] = np.nan
    finite = off[np.isfinite(off)]
    if finite.size == 0:
        sim = np.ones_like(d)
    else:
        lo, hi = float(finite.min()), float(finite.max())
        span = hi - lo if hi > lo else 1.0
        sim = 1.0 - (d - lo) / span
    sim[diag, diag] = 1.0
    return np.clip(sim, 0.0, 1.0)


def display_block(n_frames: int) -> int:
    return max(1, math.ceil(n_frames / MAX_DISPLAY))


def affinity_grid(n_panels: int) -> tuple[int, int]:
    """``(rows, columns)`` for ground truth plus the methods."""
    cols = min(MAX_COLUMNS, n_panels)
    return math.ceil(n_panels / cols), cols


def affinity_figure_size(n_methods: int) -> tuple[float, float]:
    rows, _ = affinity_grid(n_methods + 1)
    return 2 * style.COLUMN_WIDTH, round(BARS_HEIGHT + rows * PANEL_HEIGHT, 2)


def affinity_figure(gt_positive: np.ndarray, distances: Mapping[str, np.ndarray],
                    radius: float | None = None, step: int = 1,
                    n_frames: int | None = None) -> Figure:
    """Ground truth (bool N×N) beside each method's distance matrix (N×N).

    The image of panel k has gid ``"affinity:ground-truth"`` or
    ``"affinity:<name>"``; its array is the (block-reduced) similarity drawn.
    ``radius`` (metres) labels what a positive pair is. ``step`` > 1 says the
    matrices hold every ``step``-th frame of ``n_frames`` (a decimated
    affinity): the axes keep frame numbers and the title says so.
    """
    n = gt_positive.shape[0]
    block = display_block(n)
    gt = block_reduce(gt_positive.astype(np.float32), block, "max")
    idx = np.arange(gt.shape[0])
    gt[idx, idx] = 1.0
    panels = [("ground-truth", "Ground truth", gt)]
    for name, matrix in distances.items():
        reduced = block_reduce(matrix, block, "min")
        panels.append((name, f"{style.method_label(name)}\n{_range_text(matrix)}",
                       similarity(reduced)))

    rows, cols = affinity_grid(len(panels))
    with style.context():
        fig = style.new_figure(*affinity_figure_size(len(panels) - 1))
        axes = fig.subplots(rows, cols, squeeze=False, sharex=True, sharey=True)
        # frame indices on both axes (cell i is frame i·step)
        extent = (-0.5 * step, (n - 0.5) * step, (n - 0.5) * step, -0.5 * step)
        gt_image = sim_image = None
        for k, ax in enumerate(axes.flat):
            if k >= len(panels):
                ax.set_axis_off()
                continue
            key, title, data = panels[k]
            cmap = GT_CMAP if key == "ground-truth" else CMAP
            image = ax.imshow(data, cmap=cmap, vmin=0.0, vmax=1.0, extent=extent,
                              interpolation="nearest", gid=f"affinity:{key}")
            if key == "ground-truth":
                gt_image = image
            else:
                sim_image = image
            ax.set_title(title, pad=2, fontsize=6.5, linespacing=1.1)
            ax.xaxis.set_major_locator(MaxNLocator(3, integer=True))
            ax.yaxis.set_major_locator(MaxNLocator(3, integer=True))
            ax.tick_params(labelsize=6, length=2)
            for spine in ax.spines.values():
                spine.set_visible(True)
            # tick labels and axis names only on the outer edge of the grid
            bottom = k + cols >= len(panels)
            ax.tick_params(labelbottom=bottom, labelleft=k % cols == 0)
            if bottom:
                ax.set_xlabel("frame", labelpad=1)
            if k % cols == 0:
                ax.set_ylabel("frame", labelpad=1)
        # each colour bar sits under the panels it describes
        where = f"< {radius:g} m" if radius is not None else "within the radius"
        flat = list(axes.flat)
        gt_bar = fig.colorbar(gt_image, ax=flat[:1], location="bottom", shrink=0.8, aspect=8,
                              pad=0.03, ticks=[0.25, 0.75])
        gt_bar.ax.set_xticklabels(["no", "yes"])
        gt_bar.set_label(f"ground truth: pair {where}", fontsize=6, labelpad=1)
        gt_bar.ax.tick_params(labelsize=6, length=0)
        if sim_image is not None:
            bar = fig.colorbar(sim_image, ax=flat[1:len(panels)], location="bottom",
                               shrink=0.6, aspect=40, pad=0.03)
            bar.set_label("similarity = 1 − (d − d_min) / (d_max − d_min), normalised per "
                          "method over its off-diagonal pairs", fontsize=6, labelpad=1)
            bar.ax.tick_params(labelsize=6, length=2)
        notes = []
        if step > 1:
            of = f" of {n_frames}" if n_frames is not None else ""
            notes.append(f"decimated by {step}: frames 0, {step}, {2 * step}, … "
                         f"({n}{of} frames)")
        if block > 1:
            notes.append(f"each pixel: the most similar pair of a {block}×{block} block")
        if notes:
            fig.suptitle("; ".join(notes), fontsize=6, color="0.3")
    return fig


def _range_text(matrix: np.ndarray) -> str:
    """``d ∈ [min, max]`` over the finite off-diagonal distances."""
    d = np.asarray(matrix, dtype=np.float64)
    off = d[~np.eye(*d.shape, dtype=bool)] if d.ndim == 2 and d.shape[0] == d.shape[1] else d
    finite = off[np.isfinite(off)]
    if not finite.size:
        return "no finite distance"
    return f"d ∈ [{finite.min():.3g}, {finite.max():.3g}]"
