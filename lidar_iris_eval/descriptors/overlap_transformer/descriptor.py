"""OverlapTransformer (Ma, Zhang, Xu, Ai, Gu, Chen; RA-L 2022) as a liris method.

A scan becomes OverlapNet's 64 x 900 depth image (:mod:`.projection`), the
network (:mod:`.network`, NumPy) turns it into a 256-d unit vector, and two
scans are compared as the authors' evaluation does: the squared L2 distance
of faiss' ``IndexFlatL2`` (``metric="l2sq"``, in ``[0, 4]``; ``2 - 2 cos``
for unit vectors). ``"l2"`` and ``"cosine"`` (``1 - cos``) rank identically.
No yaw is estimated (the descriptor is yaw-invariant by construction).

Weights: ``weights=PATH`` reads the user's checkpoint (the authors'
``pretrained_overlap_transformer.pth.tar`` or any ``torch.save`` of a model
with their parameter names, :mod:`.checkpoint`, no torch needed), or an
``.npz`` of the same names. Without it the method runs on **deterministic
random weights** (``weights="random-init"``): NOT a trained model; see
MODEL_CARD.md. The SHA-256 of the weights enters the cache key.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidar_iris_eval.descriptors import checkpoint
from lidar_iris_eval.descriptors.base import Descriptor
from lidar_iris_eval.descriptors.overlap_transformer import network, projection
from lidar_iris_eval.descriptors.vector_common import finite_xyz, pairwise_blocks
from lidar_iris_eval.descriptors.vector_common import vector_rows as _rows
from lidar_iris_eval.errors import LirisError, warn

RANDOM_INIT = "random-init"
_METRICS = ("l2sq", "l2", "cosine")


@dataclass(frozen=True)
class OverlapTransformerParams:
    """Parameters; the defaults are the authors' (KITTI HDL-64E).

    Attributes
    ----------
    height, width : int
        Range image size (64 x 900). The network needs 64 rows.
    fov_up, fov_down : float
        Vertical field of view of the projection, degrees (+3, -25).
    max_range : float
        Points at or beyond this range are dropped (80 m, OverlapNet's default).
    depth_format : str
        ``"png"``: depths rounded to whole metres, empty pixels 0 (the 8-bit PNG
        the authors trained and tested on); ``"float"``: the in-code float image,
        empty pixels -1 (see :mod:`.projection`).
    weights : str
        ``"random-init"`` (deterministic random weights, not trained), or the
        path of a ``.pth`` / ``.pth.tar`` checkpoint or an ``.npz``.
    seed : int
        Seed of the random weights (only with ``weights="random-init"``).
    metric : str
        ``"l2sq"`` (the authors' faiss distance), ``"l2"`` or ``"cosine"``.
    """

    height: int = 64
    width: int = 900
    fov_up: float = 3.0
    fov_down: float = -25.0
    max_range: float = 80.0
    depth_format: str = "png"
    weights: str = RANDOM_INIT
    seed: int = 0
    metric: str = "l2sq"


class OverlapTransformer(Descriptor):
    """OverlapTransformer: 256-d learned global descriptor, squared L2, no yaw."""

    name = "overlap-transformer"
    label = "OverlapTransformer"
    color = "#882255"
    params_type = OverlapTransformerParams
    symmetric = True

    def __init__(self, params: OverlapTransformerParams | None = None, preset: str = "custom"):
        super().__init__(params, preset)
        p = self.params
        source = f"overlap-transformer preset {preset}"
        if p.depth_format not in projection.DEPTH_FORMATS:
            raise LirisError(source, f"depth_format must be one of "
                             f"{', '.join(projection.DEPTH_FORMATS)}, got {p.depth_format!r}")
        if p.metric not in _METRICS:
            raise LirisError(source, f"metric must be one of {', '.join(_METRICS)}, "
                             f"got {p.metric!r}")
        if network.conv_height(p.height) != 1 or p.width < 1:
            raise LirisError(source, f"the eleven convolutions must reduce the image height "
                             f"to one row (64 does), got {p.height} x {p.width}")
        if not p.fov_up > p.fov_down:
            raise LirisError(source, f"fov_up ({p.fov_up}) must exceed fov_down ({p.fov_down})")
        self._weights: dict | None = None
        self._digest: str | None = None
        self._kernel = functools.partial(_rows, metric=p.metric)

    def __getstate__(self) -> dict:
        """Picklable (worker processes) without the 74 MB of weights: reloaded on use."""
        state = dict(self.__dict__)
        state["_weights"] = None
        return state

    # ------------------------------------------------------------------ weights

    @property
    def trained(self) -> bool:
        """False for the shipped random weights."""
        return self.params.weights != RANDOM_INIT

    def _error(self, problem: str) -> LirisError:
        return LirisError(f"overlap-transformer.weights={self.params.weights}", problem)

    def weights(self) -> dict[str, np.ndarray]:
        """The network's float32 weights by name (loaded once)."""
        if self._weights is None:
            if not self.trained:
                warn("overlap-transformer.weights=random-init",
                     "deterministic random weights, NOT a trained model (scores are not "
                     "OverlapTransformer's); give a checkpoint with "
                     "--param overlap-transformer.weights=PATH")
                w = network.random_weights(self.params.seed)
                self._digest = network.weights_digest(w)
            else:
                w, self._digest = self._read_file(Path(self.params.weights).expanduser())
            problems = network.check_weights(w)
            if problems:
                shown = "; ".join(problems[:3]) + (f" (+{len(problems) - 3} more)"
                                                   if len(problems) > 3 else "")
                raise self._error(f"not an OverlapTransformer model: {shown}")
            self._weights = {k: np.ascontiguousarray(w[k], dtype=np.float32)
                             for k in network.shapes()}
        return self._weights

    def _read_file(self, path: Path) -> tuple[dict, str]:
        try:
            return checkpoint.read_weights_file(path)
        except OSError as err:
            raise self._error(f"cannot read {path} ({err.strerror or err})") from None
        except checkpoint.CheckpointError as err:
            raise self._error(f"{path}: {err}") from None

    def cache_token(self) -> str:
        """SHA-256 (16 hex) of the weights: the file's bytes, or the random arrays."""
        self.weights()
        return str(self._digest)[:16]

    def run_info(self) -> dict[str, Any]:
        return {"weights": Path(self.params.weights).name if self.trained else RANDOM_INIT,
                "weights_sha256": self.cache_token(), "weights_trained": self.trained,
                "depth_format": self.params.depth_format}

    # ------------------------------------------------------------------ describe

    def range_image(self, points: np.ndarray) -> np.ndarray:
        """The ``(height, width)`` depth image the network reads."""
        p = self.params
        pts = finite_xyz(points, minimum=1, dtype=np.float32, method="OverlapTransformer")
        return projection.range_image(pts, p.height, p.width, p.fov_up, p.fov_down,
                                      p.max_range, p.depth_format)

    def compute(self, points: np.ndarray) -> np.ndarray:
        """Describe one scan: ``(N, 3)`` points to a ``(256,)`` float32 unit vector."""
        return self.compute_images(self.range_image(points)[None])[0]

    def compute_images(self, images: np.ndarray) -> np.ndarray:
        """``(B, 256)`` descriptors of ``(B, height, width)`` depth images (one batch)."""
        return network.forward(self.weights(), np.asarray(images, np.float32)[:, None])

    # ------------------------------------------------------------------ distances

    def distance(self, query: np.ndarray, candidate: np.ndarray) -> tuple[float, float]:
        return float(self._kernel(query, np.asarray(candidate)[None, :])[0]), float("nan")

    def distances(self, query: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = self._kernel(query, database).reshape(len(database))
        return d, np.full(len(database), np.nan)

    def pairwise(self, queries: np.ndarray, database: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return pairwise_blocks(self._kernel, queries, database)
