"""Descriptors computed elsewhere (a learned network, another toolkit), evaluated like ours.

See :mod:`lidar_iris_eval.descriptors.external.descriptor`.
"""

from lidar_iris_eval.descriptors.external.descriptor import (
    METRICS,
    ExternalDescriptor,
    ExternalParams,
    load_external,
    parse_external_spec,
)

__all__ = [
    "METRICS",
    "ExternalDescriptor",
    "ExternalParams",
    "load_external",
    "parse_external_spec",
]
