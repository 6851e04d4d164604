"""BEVPlace++ (Luo et al., T-RO 2025): BEV density image, rotation-equivariant ResNet, NetVLAD."""

from lidar_iris_eval.descriptors.bevplace.descriptor import BEVPlace, BEVPlaceParams

__all__ = ["BEVPlace", "BEVPlaceParams"]
