"""The opt-in ``WorldParams.shape_variety`` (ESM's training worlds only)."""

from __future__ import annotations

import numpy as np

from lidar_iris_eval.simulate import labels
from lidar_iris_eval.simulate.raycast import BOX, ELLIPSOID
from lidar_iris_eval.simulate.world import CAR_TYPES, WorldParams, build_world

LINES = [np.array([[0.0, 0.0], [600.0, 0.0]])]


def _world(variety: bool):
    return build_world(LINES, np.random.default_rng([5, 1]), WorldParams(shape_variety=variety))


def _car_bodies(world) -> np.ndarray:
    """(length, height) of each parked car's body box (its lower box)."""
    p = world.prims
    out = []
    for obj in np.unique(world.objects):
        rows = np.nonzero((world.objects == obj) & (p.label == labels.CAR))[0]
        if len(rows):
            assert len(rows) == 2 and (p.kind[rows] == BOX).all()  # body and cabin
            body = rows[np.argmin(p.center[rows, 2])]
            out.append((2 * p.size[body, 0], 2 * p.size[body, 2]))
    return np.asarray(out)


def _crown_lobes(world) -> np.ndarray:
    p = world.prims
    veg = (p.label == labels.VEGETATION) & (p.kind == ELLIPSOID)
    objs = np.unique(world.objects[veg])
    return np.array([int((veg & (world.objects == o)).sum()) for o in objs])


def test_default_world_keeps_the_original_shapes():
    cars = _car_bodies(_world(False))
    assert len(cars) >= 10
    # the original car: length 3.9-4.9 m, body 0.6-0.8 m high; one ellipsoid per crown
    assert cars[:, 0].min() >= 3.9 and cars[:, 0].max() <= 4.9
    assert cars[:, 1].min() >= 0.6 and cars[:, 1].max() <= 0.8
    assert (_crown_lobes(_world(False)) == 1).all()


def test_variety_widens_cars_and_crowns():
    cars = _car_bodies(_world(True))
    assert len(cars) >= 10
    lo = min(r[0][0] for r in CAR_TYPES.values())
    hi = max(r[0][1] for r in CAR_TYPES.values())
    assert lo <= cars[:, 0].min() and cars[:, 0].max() <= hi
    # short hatchbacks and tall vans/SUVs appear, outside the default ranges
    assert (cars[:, 0] < 3.9).any() or (cars[:, 1] > 0.8).any()
    assert cars[:, 1].max() - cars[:, 1].min() > 0.3
    lobes = _crown_lobes(_world(True))
    assert lobes.max() >= 2 and (lobes == 1).any()
    assert set(np.unique(lobes)) <= {1, 2, 3}


def test_variety_is_deterministic():
    a, b = _world(True), _world(True)
    assert np.array_equal(a.prims.center, b.prims.center)
    assert np.array_equal(a.objects, b.objects)
