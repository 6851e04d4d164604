"""One look for every figure: method colours, column-width sizes, fonts.

Figures are built on :class:`matplotlib.figure.Figure` directly (never pyplot),
so plotting neither needs a display nor touches global state: the rc settings
below apply only inside :func:`context`. Sizes are fixed in inches and figures
are saved without ``bbox_inches="tight"``, so the pixel size of every file is
``size × dpi`` and a README can rely on it.
"""

from __future__ import annotations

import contextlib
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path

import matplotlib
from matplotlib.figure import Figure

#: one column of a two-column paper (IEEE: 3.5 in)
COLUMN_WIDTH = 3.5
#: raster resolution; vector formats ignore it
DPI = 300
FORMATS = ("png", "pdf", "svg")
#: formats that stay sharp at any size; a PNG is always accompanied by a PDF
VECTOR_FORMATS = ("pdf", "svg")

#: colours for methods that name none (``Descriptor.color``), picked by a stable hash of
#: the name; each method's own label and colour live in its folder under descriptors/
_SPARE_COLORS = ("#E69F00", "#56B4E9", "#8C564B", "#7F7F7F", "#000000")


def _method_attr(name: str, attr: str) -> str | None:
    """``label`` or ``color`` of the registered method ``name`` (None if unknown)."""
    from lidar_iris_eval.descriptors import registered_class

    cls = registered_class(name)
    return getattr(cls, attr, None) if cls is not None else None


def method_order() -> tuple[str, ...]:
    """The registry order: methods are always listed in it so legends line up."""
    from lidar_iris_eval.descriptors import registered_names

    return tuple(registered_names())


#: line styles that tell runs apart when `liris plot --compare` overlays them
RUN_LINESTYLES = ("-", "--", ":", "-.")

#: detection markers on the trajectory plot (true/false positive, missed revisit)
OUTCOME_COLORS = {"tp": "#009E73", "wrong": "#D55E00", "false_alarm": "#000000",
                  "missed": "#0072B2"}

RC = {
    "font.size": 8,
    "axes.titlesize": 8,
    "axes.labelsize": 8,
    "xtick.labelsize": 7,
    "ytick.labelsize": 7,
    "legend.fontsize": 6.5,
    "legend.frameon": False,
    "legend.handlelength": 1.6,
    "lines.linewidth": 1.0,
    "lines.markersize": 4,
    "axes.linewidth": 0.6,
    "xtick.major.width": 0.6,
    "ytick.major.width": 0.6,
    "xtick.major.size": 2.5,
    "ytick.major.size": 2.5,
    "axes.spines.top": False,
    "axes.spines.right": False,
    "savefig.dpi": DPI,
    "figure.dpi": 100,
    "pdf.fonttype": 42,  # embed TrueType so PDF text stays editable
    "svg.fonttype": "none",
    "image.interpolation": "nearest",
}


def method_color(name: str) -> str:
    """The colour of a descriptor, identical in every figure and every run."""
    color = _method_attr(name, "color")
    if color:
        return color
    return _SPARE_COLORS[zlib.crc32(name.encode()) % len(_SPARE_COLORS)]


def method_label(name: str) -> str:
    """Human-readable descriptor name for legends and titles."""
    return _method_attr(name, "label") or name


def method_sort_key(name: str) -> tuple[int, str]:
    """Registry order first, unknown names after them alphabetically."""
    order = method_order()
    return (order.index(name) if name in order else len(order), name)


def in_method_order(names: Iterable[str]) -> list[str]:
    """``names`` in registry order, so every figure lists the methods alike."""
    return sorted(names, key=method_sort_key)


@contextlib.contextmanager
def context() -> Iterator[None]:
    """Apply the house style for the duration of a block (build *and* save in it)."""
    with matplotlib.rc_context(RC):
        yield


def new_figure(width: float, height: float) -> Figure:
    """A figure of fixed size with constrained layout (no overlapping labels).

    Call inside :func:`context` so fonts pick up the house style.
    """
    return Figure(figsize=(width, height), layout="constrained")


def pixel_size(width: float, height: float, dpi: int = DPI) -> tuple[int, int]:
    """``(width_px, height_px)`` of a PNG saved by :func:`save`."""
    return round(width * dpi), round(height * dpi)


def save(fig: Figure, path: Path) -> Path:
    """Write ``fig``; the format comes from the suffix. Returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with context():
        fig.savefig(path, dpi=DPI, metadata=_metadata(path.suffix))
    return path


def _metadata(suffix: str) -> dict:
    """Drop creation dates so re-plotting the same run gives identical files."""
    if suffix == ".pdf":
        return {"CreationDate": None}
    if suffix == ".svg":
        return {"Date": None}
    return {}
