"""LiDAR Iris internals for one frame (the paper's Fig. 2, 4 and 5).

Pure drawing: these functions take the arrays made by
:mod:`lidar_iris_eval.descriptors.lidar_iris` (iris image, binary feature and
mask maps) and never compute descriptors themselves.

Image orientation follows the descriptor: row = range ring (near at the top),
column = azimuth sector, counter-clockwise. Rotating a scan CCW by θ moves its
image θ/Δ columns to the right (Δ = 360°/sectors), so a candidate whose yaw
relative to the query is θ is aligned by rolling it θ/Δ columns to the left.
"""

from __future__ import annotations

import numpy as np
from matplotlib.colors import PowerNorm
from matplotlib.figure import Figure

from lidar_iris_eval.plotting import style

FRAME_SIZE = (style.COLUMN_WIDTH, 3.3)
ALIGN_SIZE = (style.COLUMN_WIDTH, 2.6)
IMAGE_CMAP = "magma"
IMAGE_GAMMA = 0.35
#: grey level for masked feature bits (0 = black, 1 = white)
MASKED_GREY = 0.5


def feature_panels(features: np.ndarray, mask: np.ndarray, n_rows: int) -> list[np.ndarray]:
    """Split stacked (2·nscale·rings, sectors) maps into one image per map.

    Each image is 0/1 for the feature bit and :data:`MASKED_GREY` where the
    mask says the filter response was too weak to trust.
    """
    features = np.asarray(features, dtype=bool)
    mask = np.asarray(mask, dtype=bool)
    if features.shape != mask.shape or features.shape[0] % n_rows:
        raise ValueError(f"feature maps {features.shape} / mask {mask.shape} do not stack "
                         f"in blocks of {n_rows} rows")
    shown = np.where(mask, MASKED_GREY, features.astype(np.float64))
    return [shown[k:k + n_rows] for k in range(0, shown.shape[0], n_rows)]


def alignment_shift(yaw_deg: float, sectors: int) -> int:
    """Columns to roll the candidate image by so that it lines up with the query."""
    return -int(round(float(yaw_deg) * sectors / 360.0)) % sectors


def iris_frame_figure(image: np.ndarray, features: np.ndarray, mask: np.ndarray,
                      wavelengths: list[float] | None = None,
                      frame: int | str | None = None) -> Figure:
    """The iris image on top, and its binary maps below (real | imaginary per scale).

    ``frame`` labels the scan (its file name or id, e.g. ``"scan 000123"``).
    """
    rings, sectors = image.shape
    panels = feature_panels(features, mask, rings)
    nscale = len(panels) // 2
    with style.context():
        fig = style.new_figure(*FRAME_SIZE)
        grid = fig.add_gridspec(nscale + 1, 2, height_ratios=[1.7] + [1] * nscale)
        top = fig.add_subplot(grid[0, :])
        shown = _show_image(top, image)
        _code_bar(fig, shown, top)
        title = "LiDAR Iris image" + (f", {_scan(frame)}" if frame is not None else "")
        top.set_title(title, pad=2)
        top.set_ylabel("ring")
        top.set_xlabel("sector (azimuth, CCW)", labelpad=1)
        for s in range(nscale):
            for part in range(2):  # maps are stacked real (all scales), then imaginary
                ax = fig.add_subplot(grid[s + 1, part])
                ax.imshow(panels[part * nscale + s], cmap="gray", vmin=0, vmax=1,
                          aspect="auto", interpolation="nearest",
                          gid=f"feature:{'re' if part == 0 else 'im'}{s}")
                ax.set_xticks([])
                ax.set_yticks([])
                if s == 0:
                    ax.set_title("real part > 0" if part == 0 else "imaginary part > 0", pad=2)
                if part == 0:
                    name = f"λ={wavelengths[s]:.0f}" if wavelengths else f"scale {s}"
                    ax.set_ylabel(name, fontsize=6, rotation=0, ha="right", va="center")
        fig.supxlabel("white: bit set, black: clear, grey: masked (weak filter response)",
                      fontsize=6, color="0.3")
    return fig


def iris_alignment_figure(query: np.ndarray, candidate: np.ndarray, yaw_deg: float,
                          distance: float, frames: tuple[int, int] | None = None) -> Figure:
    """Query image, candidate image, and the candidate rolled into alignment."""
    sectors = query.shape[1]
    shift = alignment_shift(yaw_deg, sectors)
    aligned = np.roll(candidate, shift, axis=1)
    qi, ci = frames if frames else ("query", "candidate")
    titles = [
        f"query ({_scan(qi)})",
        f"candidate ({_scan(ci)})",
        f"candidate rolled {_columns(shift, sectors)} (yaw {yaw_deg:.0f}°, "
        f"d = {distance:.3f})",
    ]
    with style.context():
        fig = style.new_figure(*ALIGN_SIZE)
        axes = fig.subplots(3, 1, sharex=True)
        for ax, img, title, key in zip(axes, (query, candidate, aligned), titles,
                                       ("query", "candidate", "aligned"), strict=True):
            shown = _show_image(ax, img, gid=f"iris:{key}")
            ax.set_title(title, pad=2, fontsize=7)
            ax.set_ylabel("ring", fontsize=7)
        axes[-1].set_xlabel("sector (azimuth, CCW)")
        _code_bar(fig, shown, list(axes), aspect=30)
    return fig


def _scan(label: int | str) -> str:
    """``"scan 000123"`` for an id or file stem; the role names pass through."""
    text = str(label)
    return text if text in ("query", "candidate") else f"scan {text}"


def _code_bar(fig, image, axes, aspect: float = 12) -> None:
    """Colour bar of the pixel codes (8 height-bin bits; power scale, ticks at real codes)."""
    bar = fig.colorbar(image, ax=axes, pad=0.01, aspect=aspect, ticks=[0, 2, 8, 32, 128, 255])
    bar.set_label("code (height-bin bits)", fontsize=6)
    bar.ax.tick_params(labelsize=5.5, length=1.5)


def _show_image(ax, image: np.ndarray, gid: str = "iris:image"):
    """Pixel codes on a power scale: low height bins (the ground, code 2 on KITTI)
    give small codes that a linear scale would leave black."""
    shown = ax.imshow(image, cmap=IMAGE_CMAP, norm=PowerNorm(IMAGE_GAMMA, vmin=0, vmax=255),
                      aspect="auto", interpolation="nearest", gid=gid)
    ax.tick_params(labelsize=6, length=2)
    return shown


def _columns(shift: int, sectors: int) -> str:
    """A roll as the shortest signed move, e.g. 359 of 360 → "-1 column"."""
    signed = shift - sectors if shift > sectors // 2 else shift
    return f"{signed:+d} column{'' if abs(signed) == 1 else 's'}"
