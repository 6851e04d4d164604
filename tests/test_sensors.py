"""Sensor presets: data-sheet geometry, simulator use, `--sensor auto` and fit warnings."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import run_cli

from lidar_iris_eval.descriptors import get_descriptor
from lidar_iris_eval.errors import LirisWarning
from lidar_iris_eval.sensors import SENSORS, fit_warnings, guess_sensor, resolve_sensor
from lidar_iris_eval.simulate import build_scenario, resolve_config, simulate_sequence
from lidar_iris_eval.simulate.sensors import simulate_scan

VELODYNE = Path(__file__).resolve().parents[2] / "shared" / "data" / "kitti" / "samples" / "00"
VELODYNE = VELODYNE / "velodyne"

# (channels, lowest and highest elevation, horizontal field) from the data sheets
DATASHEET = {
    "hdl64": (64, -24.9, 2.0, 360.0),
    "hdl32": (32, -30.67, 10.67, 360.0),
    "vlp16": (16, -15.0, 15.0, 360.0),
    "vlp32": (32, -25.0, 15.0, 360.0),
    "os0-128": (128, -45.0, 45.0, 360.0),
    "os1-64": (64, -22.5, 22.5, 360.0),
    "os1-64-gen1": (64, -16.6, 16.6, 360.0),  # 2018-2019 OS1 data sheet
    "os1-128": (128, -22.5, 22.5, 360.0),
    "os2-128": (128, -11.25, 11.25, 360.0),
    "avia": (None, -38.6, 38.6, 70.4),  # 77.2 deg vertical field
    "mid360": (None, -7.0, 52.0, 360.0),
}


def test_presets_carry_the_datasheet_geometry():
    assert set(SENSORS) == set(DATASHEET)
    for name, (channels, low, high, hfov) in DATASHEET.items():
        spec = SENSORS[name]
        assert spec.vertical_fov == pytest.approx((low, high)), name
        assert spec.horizontal_fov == hfov, name
        if channels is not None:
            assert spec.channels == channels and spec.pattern == "spinning", name
        else:
            assert spec.pattern == "non-repetitive" and spec.points_per_frame > 0, name


def _one_scan(sensor: str, azimuth_steps: int | None = 360):
    cfg = resolve_config("tiny-same", dict(sensor=sensor, azimuth_steps=azimuth_steps))
    scen = build_scenario(cfg)
    return scen, simulate_scan(scen.sensor, scen.world.ground, scen.primitives(5), scen.poses[5],
                               np.random.default_rng(1))


def test_simulated_livox_avia_stays_in_its_field_and_point_budget():
    scen, scan = _one_scan("avia", azimuth_steps=None)
    az = np.degrees(np.arctan2(scan.points[:, 1], scan.points[:, 0]))
    assert np.abs(az).max() <= 70.4 / 2 + 0.2
    el = np.degrees(np.arctan2(scan.points[:, 2], np.hypot(*scan.points[:, :2].T)))
    assert el.min() >= -38.6 - 0.5 and el.max() <= 38.6 + 0.5
    # at most the data-sheet points per frame (rays into the sky return nothing)
    assert 0.3 * 24_000 < len(scan.points) <= 24_000


def test_simulated_ouster_os0_spans_its_vertical_field():
    _, scan = _one_scan("os0-128")
    el = np.degrees(np.arctan2(scan.points[:, 2], np.hypot(*scan.points[:, :2].T)))
    assert el.min() == pytest.approx(-45.0, abs=0.3)
    assert el.max() > 20.0  # walls and trees above the sensor


def test_auto_picks_hdl64_on_the_shared_kitti_scans():
    if not VELODYNE.is_dir():
        pytest.skip("../shared KITTI sample scans are not available")
    scans = [np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3]
             for f in sorted(VELODYNE.glob("*.bin"))]
    assert guess_sensor(scans[:3])[0] == "hdl64"
    assert fit_warnings(scans, -3.0, 5.0) == []  # the paper's range fits KITTI


@pytest.mark.parametrize("sensor", ["vlp16", "hdl32", "os1-64", "os1-64-gen1", "avia", "mid360"])
def test_auto_recognises_simulated_sensors(sensor):
    scen = build_scenario(resolve_config("tiny-same", dict(sensor=sensor)))
    rng = np.random.default_rng(2)
    scans = [simulate_scan(scen.sensor, scen.world.ground, scen.primitives(i), scen.poses[i],
                           rng).points for i in (0, 40, 80)]
    assert guess_sensor(scans)[0] == sensor


def test_fit_warnings_count_heights_and_coverage():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-20, 20, (20000, 2))
    z = np.r_[np.full(17600, 0.0), np.full(2400, 9.0)]  # 12 % above 5 m
    scan = np.c_[xy, z].astype(np.float32)
    problems = fit_warnings([scan], -3.0, 5.0)
    assert len(problems) == 1 and problems[0].startswith("12% of a scan's points")
    assert fit_warnings([scan], -3.0, 10.0) == []
    front = scan[scan[:, 0] > np.abs(scan[:, 1])]  # a 90-degree wedge
    assert any("cover only about" in p for p in fit_warnings([front], -3.0, 10.0))


def test_every_sensor_has_a_lidar_iris_height_range_a_road_offset_below_the_sensor():
    for name, spec in SENSORS.items():
        p = get_descriptor("lidar-iris", sensor=name).params
        if name == "vlp16":  # the paper's printed VLP-16 range, kept as printed
            assert (p.z_low, p.z_high) == (-2.0, 22.0)
            continue
        assert p.z_low == pytest.approx(-(spec.mount_height + 1.27), abs=0.01), name
        assert p.z_high - p.z_low == pytest.approx(8.0), name


def test_resolve_sensor_reports_its_choice_and_leaves_named_presets_alone():
    assert resolve_sensor("os1-64", lambda: pytest.fail("must not open")) == "os1-64"
    scen = build_scenario(resolve_config("tiny-same", dict(sensor="vlp16")))
    scans = [simulate_scan(scen.sensor, scen.world.ground, scen.primitives(i), scen.poses[i],
                           None).points for i in (0, 1, 2)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert resolve_sensor("auto", lambda: scans) == "vlp16"
    assert any(issubclass(w.category, LirisWarning) and "chose vlp16" in str(w.message)
               for w in caught)


def test_cli_sensor_auto_on_a_simulated_vlp16_sequence(tmp_path, capsys):
    seq = simulate_sequence(tmp_path / "seq", preset="tiny-same", sensor="vlp16", frames=40,
                            azimuth_steps=360)
    out = tmp_path / "run"
    code, _, err = run_cli(["eval", seq, "--protocol", "2", "--descriptor", "lidar-iris",
                            "--sensor", "auto", "--cache-dir", tmp_path / "cache", "--out", out,
                            "-q"], capsys)
    assert code == 0, err
    assert "--sensor auto: chose vlp16" in err
    config = yaml.safe_load((out / "config.yaml").read_text())
    assert config["sensor"] == "vlp16"
    assert config["descriptors"][0]["params"]["z_high"] == 22.0
