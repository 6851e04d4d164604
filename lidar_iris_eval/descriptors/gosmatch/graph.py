"""GOSMatch's two histograms of object-to-object distances.

A scan is a set of object centroids (vertices), sorted by class: vehicles,
then trunks, then poles (class codes 0, 1, 2). Distances between centroids
are 3-D Euclidean and binned into ``bins`` bins of ``bin_width`` metres,
``[k w, (k+1) w)``; everything at or beyond ``(bins - 1) w`` lands in the
last bin (the authors' loop tests the last bin's upper edge and the overflow
in the same pass, so 60 m and more all count in bin 61).

* The **graph descriptor** has one histogram per edge type, in the order
  vehicle-vehicle, vehicle-trunk, vehicle-pole, trunk-trunk, trunk-pole,
  pole-pole: ``6 * bins`` raw counts (366 with 61 bins).
* The **vertex descriptor** of vertex ``i`` has one histogram per class of
  the *other* vertex: ``3 * bins`` counts (183), its distances to every
  other vertex (never itself).

Two quirks of the authors' code (``Centroids2GraphDes.m``, ``GetVertexDes.m``)
are switchable, each with the code's and the paper's behaviour:

``pairs``: ``"ordered"`` (code)
    a same-class block loops over all ordered pairs including ``i == j``, so
    it counts every unordered pair twice and adds one zero-length edge per
    vertex; ``"unordered"`` (paper): each pair once, no self-pairs.
``offset``: ``"cumcount-bug"`` (code)
    the vertex descriptor files a neighbour ``j`` (1-based) under the first
    class whose cumulative count ``c`` satisfies ``j - 1 <= c``; the first
    vertex of every later class therefore lands in the previous class's block
    (after an empty class, in the earliest class with the same cumulative
    count); ``"exact"`` (paper): every neighbour under its own class.
"""

from __future__ import annotations

import numpy as np

N_CLASSES = 3
#: (class a, class b) of each graph block, in the authors' order
EDGE_TYPES: tuple[tuple[int, int], ...] = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
CLASS_NAMES: tuple[str, ...] = ("vehicle", "trunk", "pole")


def class_counts(classes: np.ndarray) -> np.ndarray:
    """``(3,)`` number of vertices of each class (the authors' ``bow.txt`` row)."""
    return np.bincount(np.asarray(classes, dtype=np.int64), minlength=N_CLASSES)[:N_CLASSES]


def check_sorted(classes: np.ndarray) -> None:
    """Vertices must be sorted by class: the block layout relies on it."""
    classes = np.asarray(classes)
    if classes.size and (np.any(np.diff(classes) < 0) or classes.min() < 0
                         or classes.max() >= N_CLASSES):
        raise ValueError("object classes must be sorted codes 0 (vehicle), 1 (trunk), 2 (pole)")


def distance_bins(centroids: np.ndarray, bins: int, bin_width: float) -> np.ndarray:
    """``(K, K)`` bin index of every centroid pair's 3-D distance.

    The bin of ``d`` is the number of bin edges ``k * w`` (k = 1 .. bins-1) at
    or below ``d``: exactly the authors' comparisons ``(k-1) w <= d < k w``,
    without dividing by ``w``.
    """
    c = np.asarray(centroids, dtype=np.float64)
    diff = c[:, None, :] - c[None, :, :]
    dist = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff))
    edges = np.arange(1, bins, dtype=np.float64) * bin_width
    return np.searchsorted(edges, dist, side="right")


def graph_descriptor(
    centroids: np.ndarray,
    classes: np.ndarray,
    pairs: str = "ordered",
    bins: int = 61,
    bin_width: float = 1.0,
) -> np.ndarray:
    """The ``(6 * bins,)`` float64 edge-length histograms of one scan.

    Parameters
    ----------
    centroids : ``(K, 3)`` vertex positions, sorted by class.
    classes : ``(K,)`` class codes 0/1/2, non-decreasing.
    pairs : ``"ordered"`` (ordered pairs and self-pairs inside same-class
        blocks, as the authors' code) or ``"unordered"`` (each pair once).
    """
    check_sorted(classes)
    classes = np.asarray(classes, dtype=np.int64)
    out = np.zeros((len(EDGE_TYPES), bins), dtype=np.float64)
    if len(classes) == 0:
        return out.ravel()
    b = distance_bins(centroids, bins, bin_width)
    ci, cj = classes[:, None], classes[None, :]
    if pairs == "ordered":
        # ordered pairs with ci <= cj, self-pairs included
        keep = ci <= cj
    elif pairs == "unordered":
        # each unordered pair once: ci < cj, or same class with i < j
        idx = np.arange(len(classes))
        keep = (ci < cj) | ((ci == cj) & (idx[:, None] < idx[None, :]))
    else:
        raise ValueError(f"unknown pairs {pairs!r}; use 'ordered' or 'unordered'")
    block_of = np.full((N_CLASSES, N_CLASSES), -1, dtype=np.int64)
    for k, (a, c) in enumerate(EDGE_TYPES):
        block_of[a, c] = k
    block = np.broadcast_to(block_of[ci, cj], b.shape)[keep]
    np.add.at(out, (block, b[keep]), 1.0)
    return out.ravel()


def neighbour_blocks(classes: np.ndarray, offset: str = "cumcount-bug") -> np.ndarray:
    """``(K,)`` class block under which each vertex is filed as a *neighbour*.

    ``exact``: its own class. ``cumcount-bug``: the authors' offset, the first
    class whose cumulative count ``c`` has ``j0 <= c`` for 0-based index ``j0``
    (the correct test is ``j0 < c``).
    """
    classes = np.asarray(classes, dtype=np.int64)
    if offset == "exact":
        return classes.copy()
    if offset != "cumcount-bug":
        raise ValueError(f"unknown offset {offset!r}; use 'cumcount-bug' or 'exact'")
    cum = np.cumsum(class_counts(classes))
    return np.searchsorted(cum, np.arange(len(classes)), side="left").astype(np.int64)


def vertex_descriptors(
    centroids: np.ndarray,
    classes: np.ndarray,
    offset: str = "cumcount-bug",
    bins: int = 61,
    bin_width: float = 1.0,
) -> np.ndarray:
    """``(K, 3 * bins)`` float32 per-vertex histograms of distances to the other vertices."""
    check_sorted(classes)
    k = len(classes)
    out = np.zeros((k, N_CLASSES * bins), dtype=np.float32)
    if k == 0:
        return out
    b = distance_bins(centroids, bins, bin_width)
    col = neighbour_blocks(classes, offset)[None, :] * bins + b
    rows = np.broadcast_to(np.arange(k)[:, None], (k, k))
    off = ~np.eye(k, dtype=bool)
    np.add.at(out, (rows[off], col[off]), 1.0)
    return out
