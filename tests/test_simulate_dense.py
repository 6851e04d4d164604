"""The dense urban world style (preset ``urban-dense``) and the default style's bytes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_simulate_golden import FRAMES, assert_golden

from lidar_iris_eval.cli import main
from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate import labels, resolve_config, simulate_sequence
from lidar_iris_eval.simulate.pipeline import build_scenario
from lidar_iris_eval.simulate.presets import PRESETS, manifest_config
from lidar_iris_eval.simulate.world import (
    DENSE,
    WORLD_STYLES,
    WorldParams,
    build_world,
    world_params,
)

STREET = 2000.0
LINES = [np.array([[0.0, 0.0], [STREET, 0.0]])]


def _kerb_rates(p: WorldParams) -> dict[int, float]:
    """Expected placement attempts per metre of one street side, from the parameters alone.

    Each kind is a renewal process along the side: street trees every ``tree_spacing``
    (three times it with probability ``1 - tree_regular``; plus the yard trees of empty
    lots), poles every ``light_spacing``, parked cars in runs (a run with probability
    ``parked_run`` of ``parked_run_cars`` cars spaced ``parked_spacing``, then a gap
    ``parked_gap``).
    """
    mean = lambda r: (r[0] + r[1]) / 2  # noqa: E731
    tree = mean(p.tree_spacing) * (p.tree_regular + 3.0 * (1.0 - p.tree_regular))
    # lots follow each other every frontage plus a gap; an empty lot gets 1-4 yard trees
    lot = mean(p.building_front) + (1.0 - p.no_gap) * mean(p.building_gap)
    yard_trees = p.empty_lot * 2.5 / lot
    cars = p.parked_run * (p.parked_run_cars[0] + p.parked_run_cars[1] - 1) / 2
    cycle = cars * mean(p.parked_spacing) + mean(p.parked_gap)
    return {labels.TRUNK: 1.0 / tree + yard_trees, labels.POLE: 1.0 / mean(p.light_spacing),
            labels.CAR: cars / cycle}


def _placed(p: WorldParams) -> dict[int, int]:
    """Objects of each kind placed along the straight street (by the label of their first row)."""
    world = build_world(LINES, np.random.default_rng([5, 1]), p)
    _, first = np.unique(world.objects, return_index=True)
    kinds = world.prims.label[first]
    return {k: int((kinds == k).sum()) for k in (labels.TRUNK, labels.POLE, labels.CAR)}


def test_dense_world_has_more_objects_along_the_road():
    sides = 2 * STREET
    for p in (WorldParams(), DENSE):
        placed = _placed(p)
        for kind, rate in _kerb_rates(p).items():
            # never more than were attempted (up to the randomness of the draws), and
            # parked cars (on the road, rarely refused) come close to the expected count
            assert placed[kind] <= 1.25 * rate * sides + 5, (kind, placed[kind], rate * sides)
        assert placed[labels.CAR] >= 0.7 * _kerb_rates(p)[labels.CAR] * sides
    default, dense = _placed(WorldParams()), _placed(DENSE)
    expected_default = sum(_kerb_rates(WorldParams()).values())
    expected_dense = sum(_kerb_rates(DENSE).values())
    assert expected_dense > 2.5 * expected_default  # the parameters say so...
    assert sum(dense.values()) > 2.5 * sum(default.values())  # ...and the world has them
    # the dense world's own additions exist only there
    dense_world = build_world(LINES, np.random.default_rng([5, 1]), DENSE)
    default_world = build_world(LINES, np.random.default_rng([5, 1]), WorldParams())
    assert (dense_world.prims.label == labels.OTHER_STRUCTURE).any()
    assert not (default_world.prims.label == labels.OTHER_STRUCTURE).any()


def test_urban_dense_is_small_mixed_in_a_denser_world():
    dense, small = resolve_config("urban-dense", {}), resolve_config("small-mixed", {})
    assert dense.world_style == "dense" and small.world_style == "default"
    assert {**PRESETS["urban-dense"], "world_style": "default"} == {
        **PRESETS["small-mixed"], "world_style": "default"}
    a, b = build_scenario(dense), build_scenario(small)
    np.testing.assert_array_equal(a.poses[:, :2, 3], b.poses[:, :2, 3])  # the same drive
    assert len(np.unique(a.world.objects)) > 2 * len(np.unique(b.world.objects))
    assert world_params("default") == WorldParams() and WORLD_STYLES["dense"] is DENSE


def test_default_style_keeps_the_golden_bytes(tmp_path):
    # the default style, asked for explicitly, goes through the new code path (every new
    # WorldParams field at its default) and must give the bytes of the code before it
    # the golden tiny-mixed run; as a byte digest it equalled the output of commit f00cc22
    # (before world styles existed), and the fingerprint was retaken from unchanged code
    frames = FRAMES["tiny-mixed"]
    out = simulate_sequence(tmp_path / "seq", "tiny-mixed", frames=frames,
                            world_style="default")
    assert_golden(out, "tiny-mixed")
    manifest = json.loads((out / "manifest.json").read_text())
    assert "world_style" not in manifest["config"] and "world_params" not in manifest
    assert manifest["config"] == json.loads(json.dumps(
        manifest_config(resolve_config("tiny-mixed", {"frames": frames}))))


def test_urban_dense_end_to_end_through_the_cli(tmp_path):
    out = tmp_path / "ud"
    main(["simulate", str(out), "--world", "urban-dense", "--frames", "3", "-q"])
    assert len(list((out / "velodyne").glob("*.bin"))) == 3
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["preset"] == "urban-dense" and manifest["config"]["world_style"] == "dense"
    assert manifest["world_params"]["buildings_first"] is True
    assert manifest["classes"][str(labels.OTHER_STRUCTURE)] == "other-structure"


def test_unknown_world_style_is_one_clear_error():
    with pytest.raises(LirisError, match="world style"):
        resolve_config("small-mixed", {"world_style": "mega"})
