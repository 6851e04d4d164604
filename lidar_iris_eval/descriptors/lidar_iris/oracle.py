"""How often a LiDAR Iris shift search reaches the exhaustive-best shift on a sequence.

The exhaustive search (all ``sectors`` column shifts) is the oracle. On every
pair of frames closer than ``near`` metres the study compares the distance a
search returns with the oracle's. It also splits those pairs into two kinds,
because the question "did the search find the best alignment?" only has a
useful answer for one of them:

* **recognisable** pairs: the oracle's distance is below the ``quantile`` of
  the oracle distances of unrelated pairs (frames more than ``far`` metres
  apart) in the same sequence, so some threshold could accept the pair while
  rejecting 99 % of unrelated places (with the default ``quantile=0.01``);
* **weak** pairs: the best alignment is no better than that of unrelated
  places. Their distance curve over the shifts is as flat as an unrelated
  pair's, its minimum is a coin toss among near-equal shifts, and no
  threshold with useful precision would accept the pair, whichever shift wins.

The split is made by the oracle, not by the search under test, so a search
cannot improve its figure by making pairs look weak.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from lidar_iris_eval.descriptors.lidar_iris.descriptor import LidarIris


@dataclass
class SearchAgreement:
    """Per-pair results of one search against the oracle (see the module docstring)."""

    #: (P, 2) frame indices of the near pairs (i < j)
    pairs: np.ndarray
    #: (P,) metres between the two frames
    metres: np.ndarray
    #: (P,) oracle (exhaustive-best) distance and the search's distance
    best: np.ndarray
    found: np.ndarray
    #: oracle distance below which a pair is recognisable
    threshold: float
    #: oracle distances of the sampled unrelated pairs
    unrelated: np.ndarray = field(repr=False)

    @property
    def excess(self) -> np.ndarray:
        """How far above the best distance the search ended, per pair (>= 0)."""
        return self.found - self.best

    @property
    def recognisable(self) -> np.ndarray:
        return self.best < self.threshold

    def rate(self, mask: np.ndarray | None = None, tolerance: float = 0.0) -> float | None:
        """Share of (masked) pairs within ``tolerance`` of the best; None without pairs."""
        excess = self.excess if mask is None else self.excess[mask]
        return float(np.mean(excess <= tolerance)) if excess.size else None


def _pair_distances(desc: LidarIris, descs: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """Distances of the listed pairs, one kernel call per query frame."""
    out = np.empty(len(pairs))
    for i in np.unique(pairs[:, 0]):
        rows = np.nonzero(pairs[:, 0] == i)[0]
        out[rows] = desc.distances(descs[i], descs[pairs[rows, 1]])[0]
    return out


def search_agreement(
    desc: LidarIris,
    descs: np.ndarray,
    positions: np.ndarray,
    near: float = 4.0,
    far: float = 15.0,
    quantile: float = 0.01,
    unrelated_pairs: int = 2000,
    seed: int = 0,
) -> SearchAgreement:
    """Compare ``desc``'s shift search with the exhaustive oracle on a sequence.

    Parameters
    ----------
    desc : LidarIris
        The descriptor whose ``shift_search`` is tested; the oracle uses its
        parameters with ``shift_search="exhaustive"``.
    descs : ndarray
        Stacked descriptors of the sequence's frames.
    positions : ndarray
        (N, 3) sensor positions, metres.
    near, far : float
        Pairs closer than ``near`` are tested; pairs farther than ``far`` are
        the unrelated reference.
    quantile : float
        Quantile of the unrelated oracle distances that separates
        recognisable from weak pairs.
    unrelated_pairs : int
        Unrelated pairs sampled (seeded) to estimate that quantile.
    seed : int
        Seed of the sample.
    """
    import dataclasses

    oracle = LidarIris(dataclasses.replace(desc.params, shift_search="exhaustive"))
    positions = np.asarray(positions, dtype=float)
    gap = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=2)
    upper = np.triu(np.ones_like(gap, dtype=bool), k=1)
    near_pairs = np.argwhere(upper & (gap < near))
    far_pairs = np.argwhere(upper & (gap > far))
    rng = np.random.default_rng(seed)
    if len(far_pairs) > unrelated_pairs:
        far_pairs = far_pairs[np.sort(rng.choice(len(far_pairs), unrelated_pairs, replace=False))]
    unrelated = _pair_distances(oracle, descs, far_pairs)
    unrelated = unrelated[np.isfinite(unrelated)]
    threshold = float(np.quantile(unrelated, quantile)) if unrelated.size else np.inf
    return SearchAgreement(
        pairs=near_pairs,
        metres=gap[near_pairs[:, 0], near_pairs[:, 1]],
        best=_pair_distances(oracle, descs, near_pairs),
        found=_pair_distances(desc, descs, near_pairs),
        threshold=threshold,
        unrelated=unrelated,
    )
