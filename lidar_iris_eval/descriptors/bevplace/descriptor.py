"""BEVPlace++ (Luo et al., T-RO 2025) as a liris method: retrieval and a 3-DoF pose.

A scan becomes the authors' 201 x 201 BEV density image (:mod:`.bev`), the
network (:mod:`.network`, NumPy) turns it into an 8192-d unit vector, and two
scans are compared as the authors' evaluation does: the squared L2 distance of
faiss' ``IndexFlatL2`` (``metric="l2sq"``, ``2 - 2 cos`` for unit vectors).
Each protocol 1 match then gets the authors' planar pose (x, y, yaw; z, roll
and pitch 0): FAST keypoints of the two BEV images, their local features
(the REM's second output), nearest-neighbour matches and a 2-point RANSAC
(:mod:`.pose`). The pose does not change the match or its distance.

``compute`` returns a feature set: ``global`` (8192 float32), ``keypoints``
(``(K, 2)`` int16 pixels, row and column) and ``local`` (``(K, 128)`` int8,
``round(127 v)`` of the unit local features): 576 to 653 keypoints and 74 to
84 kB on the KITTI samples, beside the 32 kB global vector.

Weights: by default the file liris fitted on simulated worlds
(:data:`SHIPPED_WEIGHTS`, ``scripts/train_bevplace.py``: the random-init
encoder with a NetVLAD fitted by k-means): NOT the authors' KITTI weights;
see MODEL_CARD.md. ``weights=PATH`` reads the user's checkpoint
(the authors' ``runs/<run>/model_best.pth.tar``, or any ``torch.save`` of a
model with their parameter names; :mod:`lidar_iris_eval.descriptors.checkpoint`,
no torch needed), or an ``.npz`` of the same names; a bare file name shipped
beside this module is that file. ``weights="random-init"`` (preset
``random-init``) gives the deterministic random weights, not a trained model.
The SHA-256 of the weights (the file's bytes) enters the cache key.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lidar_iris_eval.descriptors.bevplace import bev, fast, network, pose
from lidar_iris_eval.descriptors.features import RaggedFeatures
from lidar_iris_eval.descriptors.learned import LearnedVectorDescriptor, resolve_shipped
from lidar_iris_eval.descriptors.vector_common import finite_xyz
from lidar_iris_eval.errors import LirisError

#: the weights liris fitted on simulated worlds, shipped beside this module (float32);
#: not the authors' (MODEL_CARD.md)
SHIPPED_WEIGHTS = "bevplace_sim_weights.npz"
WEIGHTS_DIR = Path(__file__).resolve().parent


def resolve_weights(name: str | Path) -> Path:
    """The file ``name`` means: a bare file name shipped beside this module, else a path."""
    return resolve_shipped(name, WEIGHTS_DIR)


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
        :data:`SHIPPED_WEIGHTS` (liris' simulated-world fit, not the
        authors'), ``"random-init"`` (deterministic random weights, not
        trained), or the path of a ``.pth`` / ``.pth.tar`` checkpoint or an ``.npz``.
    seed : int
        Seed of the random weights (only with ``weights="random-init"``).
    metric : str
        ``"l2sq"`` (the authors' faiss distance), ``"l2"`` or ``"cosine"``.
    keypoint_threshold : int
        FAST threshold on the 8-bit BEV image (10: OpenCV's default, which the
        authors use, ``kitti_dataset.py`` line 85).
    ransac_iterations : int
        2-point hypotheses of the pose RANSAC (1000, ``RANSAC.py`` line 32).
    inlier_threshold : float
        Metres within which a moved keypoint is an inlier (0.5, ``RANSAC.py`` line 44).
    pixel_offset : float
        Where in its pixel a keypoint lies, in pixels toward the far corner: 0
        is the authors' (``kitti_dataset.py`` line 107: ``(100 - row) 0.4``, the
        corner toward the sensor), 0.5 the pixel's centre.
    ransac_seed : int
        Seed of the RANSAC draws (with the pair's indices; not the authors').
    pose : bool
        Estimate the pose of each protocol 1 match (the keypoints are stored either way).
    """

    bev_range: float = bev.BEV_RANGE
    voxel_size: float = bev.VOXEL_SIZE
    count_cap: int = bev.COUNT_CAP
    rotations: int = network.ROTATIONS
    weights: str = SHIPPED_WEIGHTS
    seed: int = 0
    metric: str = "l2sq"
    keypoint_threshold: int = fast.THRESHOLD
    ransac_iterations: int = pose.RANSAC_ITERATIONS
    inlier_threshold: float = pose.INLIER_THRESHOLD
    pixel_offset: float = 0.0
    ransac_seed: int = 0
    pose: bool = True


class BEVPlace(LearnedVectorDescriptor):
    """BEVPlace++: 8192-d learned global descriptor of a BEV image, squared L2, planar pose."""

    name = "bevplace"
    label = "BEVPlace++"
    color = "#117733"
    params_type = BEVPlaceParams
    symmetric = True
    network = network
    model_name = "BEVPlace++"
    shipped_dir = WEIGHTS_DIR

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
        if int(p.ransac_iterations) < 1 or not p.inlier_threshold > 0 \
                or not 0 <= int(p.keypoint_threshold) < 255:
            raise LirisError(source, f"ransac_iterations ({p.ransac_iterations}) must be at "
                             f"least 1, inlier_threshold ({p.inlier_threshold}) positive and "
                             f"keypoint_threshold ({p.keypoint_threshold}) in [0, 255)")
        if not 0.0 <= float(p.pixel_offset) <= 1.0:
            raise LirisError(source, f"pixel_offset ({p.pixel_offset}) must be in [0, 1]")

    # ------------------------------------------------------------------ describe

    def bev_image(self, points: np.ndarray) -> np.ndarray:
        """The ``uint8`` BEV image the network reads (``/ 256``, three channels)."""
        p = self.params
        pts = finite_xyz(points, minimum=1, dtype=np.float32, method="BEVPlace++")
        return bev.bev_image(pts, p.bev_range, p.voxel_size, int(p.count_cap))

    def compute(self, points: np.ndarray) -> dict[str, np.ndarray]:
        """Describe one scan: its global vector, keypoints and int8 local features."""
        image = self.bev_image(points)
        glob, best = network.forward_with_maximum(
            self.weights(), bev.network_input(image[None]), int(self.params.rotations))
        pixels = fast.detect(image, int(self.params.keypoint_threshold))
        local = network.local_features(best[0], pixels, image.shape)
        return {"global": glob[0], "keypoints": pixels.astype(np.int16),
                "local": pose.quantise(local)}

    def compute_images(self, images: np.ndarray) -> np.ndarray:
        """``(B, 8192)`` global descriptors of ``(B, S, S)`` 8-bit BEV images (one batch)."""
        return network.forward(self.weights(), bev.network_input(images),
                               int(self.params.rotations))

    # ------------------------------------------------------------------ distances

    @staticmethod
    def vectors(features) -> np.ndarray:
        """The global vectors of features: ``(N, 8192)`` (or ``(8192,)`` for one scan)."""
        if isinstance(features, RaggedFeatures):
            return features.stacked("global")
        if isinstance(features, dict):
            return features["global"]
        return np.asarray(features)

    def distance(self, query, candidate) -> tuple[float, float]:
        return super().distance(self.vectors(query), self.vectors(candidate))

    def distances(self, query, database) -> tuple[np.ndarray, np.ndarray]:
        return super().distances(self.vectors(query), self.vectors(database))

    def pairwise(self, queries, database) -> tuple[np.ndarray, np.ndarray]:
        return super().pairwise(self.vectors(queries), self.vectors(database))

    # ------------------------------------------------------------------ pose

    def pair_pose(self, query: int, candidate: int, q_feat: dict, c_feat: dict
                  ) -> tuple[np.ndarray, int]:
        """The planar pose (candidate -> query, NaN if none) and inliers of one pair."""
        p = self.params
        side = bev.image_size(p.bev_range, p.voxel_size)
        rng = np.random.default_rng([int(p.ransac_seed), int(query), int(candidate)])
        return pose.match_pose(q_feat["keypoints"], q_feat["local"], c_feat["keypoints"],
                               c_feat["local"], side, float(p.voxel_size), rng,
                               int(p.ransac_iterations), float(p.inlier_threshold),
                               float(p.pixel_offset))

    def estimate_poses(self, features, query: np.ndarray, match: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray] | None:
        """Poses ``(Q, 4, 4)`` and inliers ``(Q,)`` of protocol 1's matches (NaN without)."""
        if not self.params.pose or not isinstance(features, RaggedFeatures):
            return None
        poses = np.full((len(query), 4, 4), np.nan)
        inliers = np.zeros(len(query), dtype=np.int64)
        for n, (i, j) in enumerate(zip(query, match, strict=True)):
            if j >= 0:
                poses[n], inliers[n] = self.pair_pose(int(i), int(j), features[int(i)],
                                                      features[int(j)])
        return poses, inliers
