"""GOSMatch (Zhu et al., IROS 2020): semantic-object graphs with geometric verification."""

from lidar_iris_eval.descriptors.gosmatch.descriptor import GOSMatch, GOSMatchDB, GOSMatchParams
from lidar_iris_eval.descriptors.gosmatch.graph import (
    CLASS_NAMES,
    EDGE_TYPES,
    graph_descriptor,
    neighbour_blocks,
    vertex_descriptors,
)
from lidar_iris_eval.descriptors.gosmatch.retrieval import PrefixKNN
from lidar_iris_eval.descriptors.gosmatch.semantics import (
    ClusterSettings,
    euclidean_clusters,
    objects_from_labels,
)
from lidar_iris_eval.descriptors.gosmatch.verification import VerifySettings, verify_pair

__all__ = [
    "CLASS_NAMES",
    "EDGE_TYPES",
    "ClusterSettings",
    "GOSMatch",
    "GOSMatchDB",
    "GOSMatchParams",
    "PrefixKNN",
    "VerifySettings",
    "euclidean_clusters",
    "graph_descriptor",
    "neighbour_blocks",
    "objects_from_labels",
    "verify_pair",
    "vertex_descriptors",
]
