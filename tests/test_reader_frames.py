"""Every reader returns z-up scans (liris's x forward, y left, z up), whatever the dataset stores.

Each test writes the scans in the dataset's *native* sensor frame (tests/
dataset_writers.py writes the bytes), with the road 1.6 m below the sensor:
at z = +1.6 where the dataset's frame is z-down (Oxford, NCLT), at z = -1.6
elsewhere. Read back, the road must be 1.6 m *below* the sensor. For the two
z-down datasets the x axis must also point forward on the vehicle, checked
against the dataset's own extrinsics (not the reader's rotation).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from dataset_writers import (
    NCLT_T_BODY_VELO,
    Case,
    loop_case,
    oxford_ins_to_lidar,
    oxford_png_bytes,
    write_apollo,
    write_boreas,
    write_helipr,
    write_kitti360,
    write_mulran,
    write_nclt,
    write_newer_college,
    write_nuscenes,
    write_oxford_bin,
    write_oxford_png,
    write_wild_v3,
    write_wild_v12,
)
from PIL import Image

from lidar_iris_eval.errors import LirisWarning
from lidar_iris_eval.io import open_sequence

HEIGHT = 1.6  # m: the road below the sensor


def _road(rng: np.random.Generator, down: float) -> np.ndarray:
    """A road disc 3-15 m around the sensor at ``down`` along the native z axis,
    plus a wall 10 m ahead along native +x (so the frame's orientation shows)."""
    a = rng.uniform(-np.pi, np.pi, 400)
    r = rng.uniform(3, 15, 400)
    road = np.c_[r * np.cos(a), r * np.sin(a), np.full(400, down)]
    wall = np.c_[np.full(50, 10.0), rng.uniform(-3, 3, 50), rng.uniform(-1, 1, 50)]
    return np.concatenate([road, wall])


def _native_case(z_down: bool) -> Case:
    """The loop case's poses and times with road scans in the native frame."""
    case = loop_case(21)
    rng = np.random.default_rng(21)
    down = HEIGHT if z_down else -HEIGHT
    scans = [_road(rng, down) for _ in case.scans]
    return Case(scans, [rng.uniform(0, 100, len(s)) for s in scans], case.poses, case.times)


def _open(path, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LirisWarning)
        return open_sequence(path, **options)


WRITERS = {
    "mulran": (False, lambda t, c: write_mulran(t, c)),
    "nclt": (True, lambda t, c: write_nclt(t, c)),
    "nclt-hits": (True, lambda t, c: write_nclt(t, c, hits=True) / "velodyne_hits.bin"),
    "oxford": (True, lambda t, c: write_oxford_bin(t, c) / "velodyne_left"),
    "helipr-Ouster": (False, lambda t, c: write_helipr(t, c, "Ouster")),
    "helipr-Velodyne": (False, lambda t, c: write_helipr(t, c, "Velodyne")),
    "helipr-Aeva": (False, lambda t, c: write_helipr(t, c, "Aeva")),
    "helipr-Avia": (False, lambda t, c: write_helipr(t, c, "Avia")),
    "wild-places-v3": (False, lambda t, c: write_wild_v3(t, c)),
    "wild-places": (False, lambda t, c: write_wild_v12(t, c)),
    "newer-college": (False, lambda t, c: write_newer_college(t, c)),
    "nuscenes": (False, lambda t, c: write_nuscenes(t, c)),
    "boreas": (False, lambda t, c: write_boreas(t, c)),
    "apollo": (False, lambda t, c: write_apollo(t, c)),
    "kitti360": (False, lambda t, c: write_kitti360(t, c)[0]),
}


@pytest.mark.parametrize("name", sorted(WRITERS))
def test_the_road_is_below_the_sensor(tmp_path, name):
    z_down, write = WRITERS[name]
    case = _native_case(z_down)
    path = write(tmp_path, case)
    seq = _open(path, **({"scene": "scene-0061"} if name == "nuscenes" else {}))
    points = seq.scan(0).points
    road = np.abs(np.abs(points[:, 2]) - HEIGHT) < 0.05
    assert road.sum() >= 400  # every road point read back (NCLT: 5 mm steps)
    np.testing.assert_allclose(points[road, 2], -HEIGHT, atol=0.01)
    assert np.median(points[:, 2]) < -1.5
    # the frame is rotated, not mirrored: the wall keeps its distance and side of the road
    wall = np.abs(points[:, 2]) < 1.01
    assert wall.sum() == 50
    assert np.allclose(np.hypot(points[wall, 0], points[wall, 1]).min(), 10.0, atol=0.01)


def _forward_and_up(seq_pose: np.ndarray, vehicle_pose: np.ndarray) -> tuple:
    """The read LiDAR frame's x and z axes in a vehicle frame that is x forward, z down."""
    rotation = (np.linalg.inv(vehicle_pose) @ seq_pose)[:3, :3]
    return rotation[:, 0], rotation[:, 2]


def test_oxford_x_points_forward_and_z_up_on_the_car(tmp_path):
    case = _native_case(True)
    seq = _open(write_oxford_bin(tmp_path, case) / "velodyne_left")
    ins = case.poses[0] @ np.linalg.inv(oxford_ins_to_lidar())  # the INS: x fwd, y right, z down
    x_axis, z_axis = _forward_and_up(seq.poses[0], ins)
    assert x_axis @ np.array([1.0, 0, 0]) > np.cos(np.radians(5))
    assert z_axis @ np.array([0, 0, -1.0]) > np.cos(np.radians(5))
    # the wall written 10 m ahead along the SDK's x (the car's back) now lies behind
    points = seq.scan(0).points
    wall = np.abs(points[:, 2]) < 1.01
    assert np.all(points[wall, 0] < -9.9)
    # world points are unchanged by the rotation
    world_read = points @ seq.poses[0][:3, :3].T + seq.poses[0][:3, 3]
    world_native = case.scans[0] @ case.poses[0][:3, :3].T + case.poses[0][:3, 3]
    np.testing.assert_allclose(world_read, world_native, atol=1e-4)


def test_nclt_x_points_forward_and_z_up_on_the_segway(tmp_path):
    case = _native_case(True)
    seq = _open(write_nclt(tmp_path, case))
    body = case.poses[0] @ np.linalg.inv(NCLT_T_BODY_VELO)  # body: x fwd, y right, z down
    x_axis, z_axis = _forward_and_up(seq.poses[0], body)
    assert x_axis @ np.array([1.0, 0, 0]) > np.cos(np.radians(5))
    assert z_axis @ np.array([0, 0, -1.0]) > np.cos(np.radians(5))
    points = seq.scan(0).points
    world_read = points @ seq.poses[0][:3, :3].T + seq.poses[0][:3, 3]
    world_native = case.scans[0] @ case.poses[0][:3, :3].T + case.poses[0][:3, 3]
    np.testing.assert_allclose(world_read, world_native, atol=0.01)


def test_oxford_raw_png_road_below(tmp_path):
    """Raw firings of the SDK's elevation table: beams with a positive SDK elevation look
    down (z-down frame); their returns on a road 1.6 m below must read back at z = -1.6."""
    from lidar_iris_eval.io.datasets.oxford import BASE_TO_FIRE_HEIGHT, HDL32E_ELEVATIONS

    case = loop_case(5)
    run, _ = write_oxford_png(tmp_path, case)
    elevation = np.asarray(HDL32E_ELEVATIONS)
    columns = 90
    ranges = np.zeros((32, columns), dtype=np.uint16)
    down = elevation > 0.05
    # SDK: z = sin(e)·r − base_to_fire  (z down); road at z = +1.6
    metres = (HEIGHT + BASE_TO_FIRE_HEIGHT) / np.sin(elevation[down])
    ranges[down] = np.round(metres / 0.002).astype(np.uint16)[:, None]
    azimuth = np.linspace(0, 35999, columns).astype(np.uint16)
    intensity = np.full((32, columns), 9, dtype=np.uint8)
    for png in sorted((run / "velodyne_left").glob("*.png")):
        Image.fromarray(oxford_png_bytes(ranges, azimuth, intensity, int(png.stem)),
                        mode="L").save(png)
    points = _open(run).scan(0).points
    assert len(points) == down.sum() * columns
    np.testing.assert_allclose(points[:, 2], -HEIGHT, atol=0.01)


def test_liris_datasets_names_each_frame_and_intensity(capsys):
    import json

    from conftest import run_cli

    from lidar_iris_eval.io.datasets import DATASETS

    code, out, err = run_cli(["datasets"], capsys)
    assert code == 0, err
    frames = [line.strip() for line in out.splitlines() if line.strip().startswith("frame:")]
    values = [line for line in out.splitlines() if line.strip().startswith("intensity:")]
    assert len(frames) == len(values) == len(DATASETS)
    assert all(len(line.split(":", 1)[1].strip()) >= 4 for line in frames + values)
    assert "turned" in DATASETS["oxford"].frame and "turned" in DATASETS["nclt"].frame
    assert "dB" in DATASETS["helipr"].intensity
    code, out, _ = run_cli(["datasets", "--json"], capsys)
    rows = json.loads(out)
    assert all(row["frame"] and row["intensity"] for row in rows)


# --- nuScenes: the car's own returns ------------------------------------------------------


def _ego_returns(rng: np.random.Generator, n: int) -> np.ndarray:
    """Returns off the car's roof and body: inside the 2 m x 2 m square around the sensor,
    at heights down to -1.8 m (elevations to about -60 deg)."""
    return np.c_[rng.uniform(-0.99, 0.99, n), rng.uniform(-0.99, 0.99, n),
                 rng.uniform(-1.8, 0.1, n)]


def _near_misses(rng: np.random.Generator) -> np.ndarray:
    """Points just outside the square (one coordinate at 1.0..1.2 m) and far ones inside
    one band (|x| < 1 but |y| = 5): all must be kept."""
    edge = np.r_[1.0, rng.uniform(1.0, 1.2, 19)]
    inner = rng.uniform(-0.9, 0.9, 20)
    side = rng.choice([-1.0, 1.0], 20)
    return np.concatenate([np.c_[edge * side, inner, np.zeros(20)],
                           np.c_[inner, edge * side, np.full(20, -1.7)],
                           np.c_[inner, np.full(20, 5.0), np.zeros(20)]])


def test_nuscenes_planted_ego_returns_are_removed_exactly(tmp_path):
    rng = np.random.default_rng(40)
    base = loop_case(10)
    scene = [np.concatenate([_near_misses(rng), _road(rng, -1.8)]) for _ in base.scans]
    planted = [_ego_returns(rng, int(0.3 * len(s))) for s in scene]
    scans, intensity, order = [], [], []
    for keep, ego in zip(scene, planted, strict=True):
        cloud = np.concatenate([keep, ego])
        perm = rng.permutation(len(cloud))  # ego returns mixed in, as in a real sweep
        scans.append(cloud[perm])
        intensity.append(np.arange(len(cloud), dtype=float)[perm])
        order.append(perm)
    root = write_nuscenes(tmp_path, Case(scans, intensity, base.poses, base.times))
    seq = _open(root, scene="scene-0061")
    for k, (keep, perm) in enumerate(zip(scene, order, strict=True)):
        scan = seq.scan(k)
        kept_rows = perm[perm < len(keep)]  # the planted rows are the last ones before perm
        assert len(scan.points) == len(keep)
        np.testing.assert_allclose(scan.points, keep[kept_rows], atol=1e-5)
        np.testing.assert_array_equal(scan.intensity, kept_rows.astype(np.float32))
    # ego_radius=0 keeps every point; a larger box takes the near misses too
    assert len(_open(root, scene="scene-0061", ego_radius=0.0).scan(0).points) == len(scans[0])
    assert len(_open(root, scene="scene-0061", ego_radius=1.3).scan(0).points) == (
        len(scene[0]) - 40)


# --- --sensor auto on each reader's scans in its native frame ----------------------------------

#: reader -> (writer, rotation taking liris's frame to the native one (None: same), ego returns)
AUTO_CASES = {
    "mulran": (lambda t, c: write_mulran(t, c), None, False),
    "nclt": (lambda t, c: write_nclt(t, c), "nclt", False),
    "oxford": (lambda t, c: write_oxford_bin(t, c) / "velodyne_left", "oxford", False),
    "helipr-Ouster": (lambda t, c: write_helipr(t, c, "Ouster"), None, False),
    "helipr-Velodyne": (lambda t, c: write_helipr(t, c, "Velodyne"), None, False),
    "helipr-Avia": (lambda t, c: write_helipr(t, c, "Avia"), None, False),
    "newer-college": (lambda t, c: write_newer_college(t, c), None, False),
    "nuscenes": (lambda t, c: write_nuscenes(t, c), None, True),
    "apollo": (lambda t, c: write_apollo(t, c), None, False),
    "kitti360": (lambda t, c: write_kitti360(t, c)[0], None, False),
}
#: the preset each reader reports, i.e. its dataset's LiDAR (from the data sheets)
AUTO_EXPECTED = {"mulran": "os1-64-gen1", "nclt": "hdl32", "oxford": "hdl32",
                 "helipr-Ouster": "os2-128", "helipr-Velodyne": "vlp16", "helipr-Avia": "avia",
                 "newer-college": "os1-64-gen1", "nuscenes": "hdl32", "apollo": "hdl64",
                 "kitti360": "hdl64"}


def _simulated_scans(preset: str, n: int = 5) -> list[np.ndarray]:
    """Street scans of the preset's beam layout (z up, x forward), from the simulator."""
    from lidar_iris_eval.simulate import build_scenario, resolve_config
    from lidar_iris_eval.simulate.sensors import simulate_scan

    azimuth = None if preset == "avia" else 512
    scen = build_scenario(resolve_config("tiny-same", dict(sensor=preset,
                                                           azimuth_steps=azimuth)))
    rng = np.random.default_rng(4)
    return [simulate_scan(scen.sensor, scen.world.ground, scen.primitives(i), scen.poses[i],
                          rng).points.astype(np.float64) for i in range(0, 20 * n, 20)]


def _car_returns(rng: np.random.Generator, n: int) -> np.ndarray:
    """The car's roof and body seen by LIDAR_TOP: |x|, |y| < 1 m, elevations down to -55 deg."""
    xy = rng.uniform(-0.95, 0.95, (n, 2))
    r = np.hypot(xy[:, 0], xy[:, 1])
    return np.c_[xy, -r * np.tan(np.radians(rng.uniform(5, 55, n)))]


@pytest.mark.parametrize("name", sorted(AUTO_CASES))
def test_sensor_auto_picks_the_readers_lidar_on_native_scans(tmp_path, name):
    from dataset_writers import NCLT_TO_LIRIS, OXFORD_TO_LIRIS

    from lidar_iris_eval.sensors import guess_sensor, sample_scans

    write, frame, ego = AUTO_CASES[name]
    expected = AUTO_EXPECTED[name]
    truth = _simulated_scans(expected)
    rng = np.random.default_rng(5)
    native = list(truth)
    if ego:  # 30 % of a nuScenes sweep are the car's own returns
        native = [np.concatenate([p, _car_returns(rng, int(0.3 * len(p)))]) for p in native]
    if frame is not None:  # liris = R · native, so native rows = liris rows · R
        rotation = {"nclt": NCLT_TO_LIRIS, "oxford": OXFORD_TO_LIRIS}[frame]
        native = [p @ rotation for p in native]
    base = loop_case(30)
    case = Case(native, [rng.uniform(0, 100, len(p)) for p in native], base.poses, base.times)
    seq = _open(write(tmp_path, case), **({"scene": "scene-0061"} if ego else {}))
    assert seq.sensor_preset == expected
    scans = [seq[0], seq[1]] if name == "kitti360" else sample_scans(seq)  # kitti360 frame 3
    chosen, reason = guess_sensor(scans)                                 # is a filler cloud
    assert chosen == expected, reason
    # the same scans as stored (z-down, with the car's returns) fool the guess: the test can fail
    if frame is not None or ego:
        assert guess_sensor([np.asarray(p, np.float32) for p in native[:3]])[0] != expected


@pytest.mark.parametrize("name", ["oxford", "nuscenes"])
def test_cli_sensor_auto_chooses_hdl32_on_oxford_and_nuscenes(tmp_path, capsys, name):
    from conftest import run_cli

    write, frame, ego = AUTO_CASES[name]
    rng = np.random.default_rng(6)
    native = _simulated_scans("hdl32")
    if ego:
        native = [np.concatenate([p, _car_returns(rng, int(0.3 * len(p)))]) for p in native]
    if frame is not None:
        from dataset_writers import OXFORD_TO_LIRIS

        native = [p @ OXFORD_TO_LIRIS for p in native]
    base = loop_case(31)
    path = write(tmp_path, Case(native, [rng.uniform(0, 100, len(p)) for p in native],
                                base.poses, base.times))
    code, _, err = run_cli(["extract", path, "-d", "scan-context", "--sensor", "auto", "-q",
                            "--frames", "0:3", "--cache-dir", tmp_path / "cache",
                            *(["--scene", "scene-0061"] if ego else [])], capsys)
    assert code == 0, err
    assert "--sensor auto: chose hdl32" in err
