"""The torch-free checkpoint reader, now shared by the learned methods.

Kept so that ``overlap_transformer.checkpoint`` still names it; the code is
:mod:`lidar_iris_eval.descriptors.checkpoint`.
"""

from lidar_iris_eval.descriptors.checkpoint import (
    CheckpointError,
    read_checkpoint,
    read_weights_file,
    state_dict,
)

__all__ = ["CheckpointError", "read_checkpoint", "read_weights_file", "state_dict"]
