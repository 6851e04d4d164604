"""BEVPlace++ (Luo et al., T-RO 2025): BEV density image, rotation-equivariant ResNet, NetVLAD."""
