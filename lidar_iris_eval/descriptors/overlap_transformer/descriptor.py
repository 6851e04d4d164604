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
``.npz`` of the same names. Without it the method runs on **liris' own weights**
(``weights="ot_sim_weights.npz"``, shipped here): trained on simulated worlds only,
NOT the authors', with NetVLAD's 65,536 x 256 projection frozen at a seeded random
matrix that is regenerated at load (:func:`network.expand_frozen`); see MODEL_CARD.md.
``weights="random-init"`` gives the deterministic random weights (not a trained
model). The SHA-256 of the weights (the file's bytes) enters the cache key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lidar_iris_eval.descriptors.learned import LearnedVectorDescriptor
from lidar_iris_eval.descriptors.overlap_transformer import network, projection
from lidar_iris_eval.descriptors.vector_common import finite_xyz
from lidar_iris_eval.errors import LirisError

#: the folder of the weights files shipped with the method (``weights=NAME``)
SHIPPED_DIR = Path(__file__).resolve().parent
#: liris' own weights, trained on simulated worlds (MODEL_CARD.md; not the authors')
SIM_WEIGHTS = "ot_sim_weights.npz"


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
        ``"ot_sim_weights.npz"`` (liris' own weights trained on simulated worlds,
        shipped beside this module; not the authors'), ``"random-init"``
        (deterministic random weights, not trained), the name of another file
        shipped here, or the path of a ``.pth`` / ``.pth.tar`` checkpoint or an ``.npz``.
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
    weights: str = SIM_WEIGHTS
    seed: int = 0
    metric: str = "l2sq"


class OverlapTransformer(LearnedVectorDescriptor):
    """OverlapTransformer: 256-d learned global descriptor, squared L2, no yaw."""

    name = "overlap-transformer"
    label = "OverlapTransformer"
    color = "#882255"
    params_type = OverlapTransformerParams
    symmetric = True
    network = network
    model_name = "OverlapTransformer"
    shipped_dir = SHIPPED_DIR

    def __init__(self, params: OverlapTransformerParams | None = None, preset: str = "custom"):
        super().__init__(params, preset)
        p = self.params
        source = f"overlap-transformer preset {preset}"
        if p.depth_format not in projection.DEPTH_FORMATS:
            raise LirisError(source, f"depth_format must be one of "
                             f"{', '.join(projection.DEPTH_FORMATS)}, got {p.depth_format!r}")
        if network.conv_height(p.height) != 1 or p.width < 1:
            raise LirisError(source, f"the eleven convolutions must reduce the image height "
                             f"to one row (64 does), got {p.height} x {p.width}")
        if not p.fov_up > p.fov_down:
            raise LirisError(source, f"fov_up ({p.fov_up}) must exceed fov_down ({p.fov_down})")

    def _read_file(self, path: Path) -> tuple[dict, str]:
        """The file's weights, the frozen NetVLAD projection of liris' own weights
        regenerated from its seed."""
        weights, digest = super()._read_file(path)
        try:
            return network.expand_frozen(weights), digest
        except ValueError as err:
            raise self._error(f"{path}: {err}") from None

    def run_info(self) -> dict[str, Any]:
        return {**super().run_info(), "depth_format": self.params.depth_format}

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
