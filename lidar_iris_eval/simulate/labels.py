"""SemanticKITTI class ids used by the simulator, and their surface reflectivity.

The ids are those of the SemanticKITTI label definition (``semantic-kitti.yaml``
in the semantic-kitti-api): a ``.label`` file stores ``class | instance << 16``
per point, so tools written for SemanticKITTI read simulator output unchanged.
Reflectivities are rough typical values on KITTI's [0, 1] intensity scale; they
only make the intensity channel plausible (no descriptor here relies on it).
"""

from __future__ import annotations

CAR = 10
ROAD = 40
SIDEWALK = 48
BUILDING = 50
FENCE = 51
OTHER_STRUCTURE = 52  # street furniture; only in the dense world style
OTHER_OBJECT = 99  # rocks and benches; only in the natural worlds
VEGETATION = 70
TRUNK = 71
TERRAIN = 72
POLE = 80
TRAFFIC_SIGN = 81
MOVING_CAR = 252

#: class id -> name, for manifests and documentation.
CLASS_NAMES: dict[int, str] = {
    CAR: "car",
    ROAD: "road",
    SIDEWALK: "sidewalk",
    BUILDING: "building",
    FENCE: "fence",
    VEGETATION: "vegetation",
    TRUNK: "trunk",
    TERRAIN: "terrain",
    POLE: "pole",
    TRAFFIC_SIGN: "traffic-sign",
    MOVING_CAR: "moving-car",
}
#: classes only the dense world style uses (kept out of :data:`CLASS_NAMES`, which every
#: manifest lists, so the manifests of the older presets stay byte-identical)
DENSE_CLASS_NAMES: dict[int, str] = {**CLASS_NAMES, OTHER_STRUCTURE: "other-structure"}
#: classes of the natural worlds (``forest``, ``park``; :mod:`~lidar_iris_eval.simulate.nature`):
#: the trail or path is "sidewalk", the forest floor and lawns "terrain"
NATURE_CLASS_NAMES: dict[int, str] = {
    SIDEWALK: "sidewalk", BUILDING: "building", VEGETATION: "vegetation", TRUNK: "trunk",
    TERRAIN: "terrain", POLE: "pole", OTHER_OBJECT: "other-object",
}

#: class id -> base reflectivity in [0, 1].
REFLECTIVITY: dict[int, float] = {
    CAR: 0.25,
    ROAD: 0.22,
    SIDEWALK: 0.30,
    BUILDING: 0.35,
    FENCE: 0.30,
    OTHER_STRUCTURE: 0.35,
    OTHER_OBJECT: 0.30,
    VEGETATION: 0.45,
    TRUNK: 0.35,
    TERRAIN: 0.40,
    POLE: 0.40,
    TRAFFIC_SIGN: 0.90,
    MOVING_CAR: 0.25,
}
