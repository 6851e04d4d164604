"""MapClosures (PRBonn, ICRA 2024): loop closures between local maps, as a two-stage method.

Needs the optional extra ``mapclosures`` (docs/mapclosures.md); importing this
package does not import ``map_closures``.
"""

from lidar_iris_eval.descriptors.mapclosures.descriptor import (
    ClosureTable,
    MapClosures,
    MapClosuresParams,
    run_closures,
)
from lidar_iris_eval.descriptors.mapclosures.localmap import LocalMapSettings

__all__ = ["ClosureTable", "LocalMapSettings", "MapClosures", "MapClosuresParams",
           "run_closures"]
