"""Parked cars on another day: :func:`repark` (multi-session worlds, simulate/sessions.py).

Its own module so that the scenario builder (simulate/pipeline.py) and the
sessions driver (simulate/sessions.py, which calls the builder) need not
import each other.
"""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.simulate import labels
from lidar_iris_eval.simulate.raycast import Primitives, make_primitives
from lidar_iris_eval.simulate.world import World, car_rows

#: probability that a parked car of session 0 is not there on another day
PARKED_GONE = 0.5
#: metres a replacing car may stand further along the kerb (either way)
PARKED_SHIFT = 0.5


def repark(world: World, rng: np.random.Generator) -> World:
    """The same static world with other parked cars (simulate/sessions.py's docstring).

    Parked cars are the static primitives labelled ``car``; a replacing car
    keeps its SemanticKITTI instance number and gets a new physical-object id.
    """
    prims = world.prims
    objects = world.objects
    is_car = prims.label == labels.CAR
    keep = ~is_car
    rows: list[tuple] = []
    new_objects: list[int] = []
    next_object = int(objects.max(initial=0)) + 1 if objects is not None else 1
    for instance in np.unique(prims.instance[is_car]):
        car = np.nonzero(is_car & (prims.instance == instance))[0]
        if rng.random() < PARKED_GONE:
            continue
        body = car[0]
        yaw = float(prims.yaw[body])
        shift = rng.uniform(-PARKED_SHIFT, PARKED_SHIFT)
        x = float(prims.center[body, 0]) + shift * np.cos(yaw)
        y = float(prims.center[body, 1]) + shift * np.sin(yaw)
        z_road = float(world.ground.elevation(np.array([x]), np.array([y]))[0][0])
        parts = car_rows(rng, x, y, z_road, yaw, labels.CAR, int(instance))
        rows.extend(parts)
        new_objects.extend([next_object] * len(parts))
        next_object += 1
    merged = Primitives.concat([prims.take(np.nonzero(keep)[0]), make_primitives(rows)])
    merged_objects = None
    if objects is not None:
        merged_objects = np.concatenate(
            [objects[keep], np.asarray(new_objects, dtype=np.uint32)]).astype(np.uint32)
    return World(world.ground, merged, merged_objects)
