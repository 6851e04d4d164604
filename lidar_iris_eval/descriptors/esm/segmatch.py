"""SegMatch's eigenvalue features: the baseline segment descriptor of the ESM paper.

``-d esm:segmatch`` is ESM's local-map pipeline (segmentation, target map,
retrieval by k-NN, centroid consistency and the rigid fit all shared) with this
descriptor in place of the learned network, as in the paper's comparison
(Tinchev et al., RA-L 2019, Table I, "SegMatch"). Only the descriptor differs;
every segment gets quality 1 (the network's quality weights do not exist here).

Features of one segment, from the eigenvalues ``l1 >= l2 >= l3`` of the
covariance of its points about their centroid (divided by the number of
points), normalised to ``e_i = l_i / (l1 + l2 + l3)``:

=====================  ============================
linearity              ``(e1 - e2) / e1``
planarity              ``(e2 - e3) / e1``
scattering             ``e3 / e1``
omnivariance           ``(e1 e2 e3) ** (1/3)``
anisotropy             ``(e1 - e3) / e1``
eigenentropy           ``-(e1 ln e1 + e2 ln e2 + e3 ln e3)``
change of curvature    ``e3 / (e1 + e2 + e3)``
=====================  ============================

These are the seven features SegMatch names (Dubé et al., ICRA 2017, after
Weinmann et al.), as in SegMap's
``segmatch/src/descriptors/eigenvalue_based.cpp`` (ethz-asl/segmap), which
lists the same seven. That file differs from the definitions above in ways
kept out of this implementation (facts read from it, for the record): it sorts
the eigenvalues smallest first and then uses the *smallest* as ``e1`` (so its
"linearity" is negative and its ratios are divided by the smallest eigenvalue),
scales each feature by a fixed constant (0.9 times a maximum observed on its
training data), applies the eigenentropy's scale to its last term only, and
appends two more features (``pointing_up``: 10 when the segment's vertical
extent is its smallest, else 0; and the point count over 0.9 x 13,200). SegMatch
classifies pairs of these vectors with a random forest; the shared pipeline
here takes the k-NN in the 7-d feature space by squared L2, like ESM's
embeddings (features lie in [0, 1], eigenentropy in [0, ln 3]).

Single-scan mode (``source: scan``) computes the features on the 256
resampled, normalised points of each segment (normalised eigenvalues do not
change under the isotropic normalisation, only through the resampling); the
local-map mode on every voxel of the segment.
"""

from __future__ import annotations

import numpy as np

#: the feature order of a descriptor row
FEATURES = ("linearity", "planarity", "scattering", "omnivariance", "anisotropy",
            "eigenentropy", "change_of_curvature")
DIM = len(FEATURES)


def normalised_eigenvalues(points: np.ndarray) -> np.ndarray:
    """``(e1, e2, e3)``, largest first, of the covariance of ``points`` ((N, 3)), summing to 1.

    All zeros for a single point (no spread).
    """
    pts = np.asarray(points, dtype=np.float64)[:, :3]
    centred = pts - pts.mean(axis=0)
    cov = centred.T @ centred / max(len(pts), 1)
    lam = np.clip(np.linalg.eigvalsh(cov)[::-1], 0.0, None)
    total = lam.sum()
    return lam / total if total > 0 else np.zeros(3)


def features_from_eigenvalues(e: np.ndarray) -> np.ndarray:
    """The seven features (:data:`FEATURES`) of normalised eigenvalues ``e`` ((..., 3), largest
    first); all zeros where ``e1 = 0``."""
    e = np.asarray(e, dtype=np.float64)
    e1, e2, e3 = e[..., 0], e[..., 1], e[..., 2]
    ok = e1 > 0
    safe = np.where(ok, e1, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        logs = np.where(e > 0, np.log(np.where(e > 0, e, 1.0)), 0.0)
    out = np.stack([
        (e1 - e2) / safe,
        (e2 - e3) / safe,
        e3 / safe,
        np.cbrt(e1 * e2 * e3),
        (e1 - e3) / safe,
        -(e * logs).sum(axis=-1),
        e3 / np.where(ok, e.sum(axis=-1), 1.0),
    ], axis=-1)
    return np.where(ok[..., None], out, 0.0)


def eigenvalue_features(points: np.ndarray) -> np.ndarray:
    """The seven features of one segment's points ((N, 3))."""
    return features_from_eigenvalues(normalised_eigenvalues(points))


def describe_segments(segments) -> tuple[np.ndarray, np.ndarray]:
    """``(features (S, 7) float32, quality (S,) ones)`` of a sequence of point arrays."""
    rows = [eigenvalue_features(s) for s in segments]
    feats = np.asarray(rows, dtype=np.float32).reshape(-1, DIM)
    return feats, np.ones(len(feats))
