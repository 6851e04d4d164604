"""BEVPlace++ (Luo et al., T-RO 2025) as a liris method: retrieval only.

A scan becomes the authors' 201 x 201 BEV density image (:mod:`.bev`), the
network (:mod:`.network`, NumPy) turns it into an 8192-d unit vector, and two
scans are compared as the authors' evaluation does: the squared L2 distance of
faiss' ``IndexFlatL2`` (``metric="l2sq"``, ``2 - 2 cos`` for unit vectors).
No yaw or pose is estimated yet (the authors' local features and RANSAC
3-DoF pose are not implemented).

Weights: ``weights=PATH`` reads the user's checkpoint (the authors'
``runs/<run>/model_best.pth.tar``, or any ``torch.save`` of a model with
their parameter names; :mod:`lidar_iris_eval.descriptors.checkpoint`, no
torch needed), or an ``.npz`` of the same names. Without it the method runs on
**deterministic random weights** (``weights="random-init"``): NOT a trained
model; see MODEL_CARD.md. The SHA-256 of the weights enters the cache key.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.descriptors.bevplace import bev, network
from lidar_iris_eval.descriptors.learned import RANDOM_INIT, LearnedVectorDescriptor
from lidar_iris_eval.descriptors.vector_common import finite_xyz
from lidar_iris_eval.errors import LirisError


@dataclass(frozen=True)
class BEVPlaceParams:
    """Parameters; the defaults are the authors' (``gen_bev_images.py``, ``REIN.py``).

    Attributes
    ----------
    bev_range : float
        Half-side of the square crop, metres (40): ``|x|``, ``|y|``, ``|z|`` below it.
    voxel_size : float
        Voxel of the averaging and pixel of the image, metres (0.4); with
        ``bev_range`` it sets the image side ``2 floor(range / voxel) + 1`` (201).
    count_cap : int
        Voxel means counted per pixel at most (10) before the max normalisation.
    rotations : int
        Warped copies in the rotation-equivariant module (8, every 45 degrees).
    weights : str
        ``"random-init"`` (deterministic random weights, not trained), or the
        path of a ``.pth`` / ``.pth.tar`` checkpoint or an ``.npz``.
    seed : int
        Seed of the random weights (only with ``weights="random-init"``).
    metric : str
        ``"l2sq"`` (the authors' faiss distance), ``"l2"`` or ``"cosine"``.
    """

    bev_range: float = bev.BEV_RANGE
    voxel_size: float = bev.VOXEL_SIZE
    count_cap: int = bev.COUNT_CAP
    rotations: int = network.ROTATIONS
    weights: str = RANDOM_INIT
    seed: int = 0
    metric: str = "l2sq"


class BEVPlace(LearnedVectorDescriptor):
    """BEVPlace++: 8192-d learned global descriptor of a BEV image, squared L2, no yaw."""

    name = "bevplace"
    label = "BEVPlace++"
    color = "#117733"
    params_type = BEVPlaceParams
    symmetric = True
    network = network
    model_name = "BEVPlace++"

    def __init__(self, params: BEVPlaceParams | None = None, preset: str = "custom"):
        super().__init__(params, preset)
        p = self.params
        source = f"bevplace preset {preset}"
        if not (p.voxel_size > 0 and p.bev_range > 0) or bev.image_size(
                p.bev_range, p.voxel_size) < 9:
            raise LirisError(source, f"bev_range ({p.bev_range}) and voxel_size "
                             f"({p.voxel_size}) must be positive and give an image of at "
                             "least 9 x 9 pixels")
        if int(p.rotations) < 1 or int(p.count_cap) < 1:
            raise LirisError(source, f"rotations ({p.rotations}) and count_cap "
                             f"({p.count_cap}) must be at least 1")

    # ------------------------------------------------------------------ describe

    def bev_image(self, points: np.ndarray) -> np.ndarray:
        """The ``uint8`` BEV image the network reads (``/ 256``, three channels)."""
        p = self.params
        pts = finite_xyz(points, minimum=1, dtype=np.float32, method="BEVPlace++")
        return bev.bev_image(pts, p.bev_range, p.voxel_size, int(p.count_cap))

    def compute(self, points: np.ndarray) -> np.ndarray:
        """Describe one scan: ``(N, 3)`` points to an ``(8192,)`` float32 unit vector."""
        return self.compute_images(self.bev_image(points)[None])[0]

    def compute_images(self, images: np.ndarray) -> np.ndarray:
        """``(B, 8192)`` descriptors of ``(B, S, S)`` 8-bit BEV images (one batch)."""
        return network.forward(self.weights(), bev.network_input(images),
                               int(self.params.rotations))
