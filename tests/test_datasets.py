"""The dataset registry: each reader on tiny files in its exact format, the traps, the CLI.

Byte layouts, pose frames and extrinsics are those of DATASETS.md; the files
are written by tests/dataset_writers.py, which converts the true LiDAR poses
into each dataset's frame with its own explicit rotations, so a reader passes
only if it undoes the documented conversion.
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from dataset_writers import (
    HELIPR_SWITCH,
    NCLT_TO_LIRIS,
    OXFORD_TO_LIRIS,
    Case,
    loop_case,
    nclt_decode_expected,
    nclt_encode,
    oxford_raw_expected,
    rows,
    sorted_by_azimuth,
    to_liris_points,
    to_liris_poses,
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
    xyzrpy,
)

from lidar_iris_eval.errors import LirisError, LirisWarning
from lidar_iris_eval.io import open_sequence
from lidar_iris_eval.io.datasets import DATASETS, find_dataset

POSE_ATOL = 1e-9
POINT_ATOL = 1e-5  # float32 storage


def _quiet_open(path, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LirisWarning)
        return open_sequence(path, **options)


def _check_scans(seq, case: Case, expected_points=None, atol=POINT_ATOL, intensity=True):
    for k in range(len(seq)):
        scan = seq.scan(k)
        want = case.scans[k] if expected_points is None else expected_points[k]
        np.testing.assert_allclose(scan.points, want, atol=atol)
        if intensity:
            np.testing.assert_allclose(scan.intensity, case.intensity[k], atol=1e-4)


# --- one tiny dataset per reader, for the shared checks ------------------------------------


def _mulran(tmp):
    case = loop_case(1)
    return write_mulran(tmp, case), case, "mulran"


def _nclt(tmp):
    case = loop_case(2, far=80.0)
    return write_nclt(tmp, case), case, "nclt"


def _nclt_hits(tmp):
    case = loop_case(3, far=80.0)
    session = write_nclt(tmp, case, hits=True)
    return session / "velodyne_hits.bin", case, "nclt-hits"


def _oxford(tmp):
    case = loop_case(4)
    return write_oxford_bin(tmp, case) / "velodyne_left", case, "oxford"


def _oxford_raw(tmp):
    case = loop_case(5)
    run, _ = write_oxford_png(tmp, case)
    return run, case, "oxford-raw"


def _helipr(sensor):
    def make(tmp):
        case = loop_case(6)
        return write_helipr(tmp, case, sensor), case, "helipr"
    return make


def _wild_v3(tmp):
    case = loop_case(7)
    return write_wild_v3(tmp, case), case, "wild-places-v3"


def _wild_v12(tmp):
    case = loop_case(8)
    return write_wild_v12(tmp, case), case, "wild-places"


def _ncd(tmp):
    case = loop_case(9)
    return write_newer_college(tmp, case), case, "newer-college"


def _nuscenes(tmp):
    case = loop_case(10)
    return write_nuscenes(tmp, case), case, "nuscenes"


def _boreas(tmp):
    case = loop_case(11)
    return write_boreas(tmp, case), case, "boreas"


def _apollo(tmp):
    case = loop_case(12)
    return write_apollo(tmp, case), case, "apollo"


def _kitti360(tmp):
    case = loop_case(13)
    drive, _, _ = write_kitti360(tmp, case)
    return drive, case, "kitti360"


MAKERS = {
    "mulran": _mulran, "nclt": _nclt, "nclt-hits": _nclt_hits, "oxford": _oxford,
    "oxford-raw": _oxford_raw, "helipr-Ouster": _helipr("Ouster"),
    "helipr-Velodyne": _helipr("Velodyne"), "helipr-Aeva": _helipr("Aeva"),
    "helipr-Avia": _helipr("Avia"), "wild-places-v3": _wild_v3, "wild-places": _wild_v12,
    "newer-college": _ncd, "nuscenes": _nuscenes, "boreas": _boreas, "apollo": _apollo,
    "kitti360": _kitti360,
}
EXTRA = {"nuscenes": ["--scene", "scene-0061"]}


def test_every_registered_dataset_has_a_tiny_dataset_here():
    covered = {name.split("-")[0] if name.startswith("helipr") else name for name in MAKERS}
    specific = {s.name for s in DATASETS.values() if not s.generic}
    assert specific == covered
    assert {"kitti", "folder", "rosbag"} <= set(DATASETS)


@pytest.mark.parametrize("name", sorted(MAKERS))
def test_detected_from_the_folder_with_its_preset(tmp_path, name):
    path, case, dataset = MAKERS[name](tmp_path)
    assert find_dataset(path).name == dataset
    seq = _quiet_open(path, **({"scene": "scene-0061"} if dataset == "nuscenes" else {}))
    assert seq.dataset == dataset
    assert len(seq) == (len(case.times) + 1 if dataset == "kitti360" else len(case.times))
    assert seq.times is not None and np.all(np.diff(seq.times) > 0)


@pytest.mark.parametrize("name", sorted(MAKERS))
def test_eval_protocols_1_and_2_find_the_planted_loop(tmp_path, capsys, name):
    path, case, _ = MAKERS[name](tmp_path)
    code, out, err = run_cli(["eval", path, "-d", "scan-context", "--protocol", "1",
                              "--protocol", "2", "--exclude", "2", "--pose-frame", "lidar",
                              "--cache-dir", tmp_path / "cache", "--out", tmp_path / "run",
                              "-q", "--json", *EXTRA.get(name, [])], capsys)
    assert code == 0, err
    p1, p2 = json.loads(out)["results"]
    assert (p1["protocol"], p2["protocol"]) == (1, 2)
    assert p1["n_revisits"] == 1 and p1["n_true_top1"] == 1, p1  # the last scan finds the first
    assert p2["n_positives"] == 2 and p2["ap"] == pytest.approx(1.0), p2


# --- each reader's values --------------------------------------------------------------------


def test_mulran_more_pose_rows_than_scans(tmp_path):
    path, case, _ = _mulran(tmp_path)
    n_rows = len((path / "global_pose.csv").read_text().splitlines())
    assert n_rows == 4 * len(case.times) - 3 > len(case.times)
    with pytest.warns(LirisWarning, match="dropped 1 of 6 scans"):
        seq = open_sequence(path / "Ouster")  # the Ouster folder opens the sequence too
    assert len(seq) == len(case.times) and seq.unmatched == 1
    np.testing.assert_allclose(seq.poses, case.poses, atol=POSE_ATOL)
    assert [len(seq.scan(k).points) for k in range(len(seq))] == [len(s) for s in case.scans]
    _check_scans(seq, case)
    assert seq.sensor_preset == "os1-64-gen1"


def test_nclt_uint16_coordinates_beyond_64_m(tmp_path):
    path, case, _ = _nclt(tmp_path)
    seq = _quiet_open(path)
    expected = [to_liris_points(nclt_decode_expected(nclt_encode(p, i)), NCLT_TO_LIRIS)
                for p, i in zip(case.scans, case.intensity, strict=True)]
    _check_scans(seq, case, expected, atol=1e-4, intensity=False)
    far = seq.scan(0).points
    assert far[:, :2].max() > 79.0  # int16 would have wrapped these to negative values
    raw = np.fromfile(seq.scan_paths[0], dtype="<u2").reshape(-1, 4)[:, :3]
    assert raw.max() > 32767  # the file really holds values an int16 reader misreads
    assert np.array_equal(seq.scan(0).intensity,
                          np.clip(case.intensity[0], 0, 255).astype(np.uint8).astype(np.float32))
    np.testing.assert_allclose(seq.poses, to_liris_poses(case.poses, NCLT_TO_LIRIS), atol=1e-9)


def test_nclt_nan_ground_truth_row_is_skipped_with_a_count(tmp_path):
    path, _, _ = _nclt(tmp_path)
    with pytest.warns(LirisWarning, match="skipped 1 ground-truth rows"):
        open_sequence(path)


def test_nclt_hits_split_into_revolutions(tmp_path):
    path, case, _ = _nclt_hits(tmp_path)
    seq = _quiet_open(path)
    assert len(seq) == len(case.times)
    for k in range(len(seq)):
        pts, _ = sorted_by_azimuth(case.scans[k], case.intensity[k])
        want = nclt_decode_expected(nclt_encode(pts, np.zeros(len(pts))))
        np.testing.assert_allclose(seq.scan(k).points, to_liris_points(want, NCLT_TO_LIRIS),
                                   atol=1e-4)
    np.testing.assert_allclose(seq.poses, to_liris_poses(case.poses, NCLT_TO_LIRIS), atol=1e-9)
    np.testing.assert_allclose(seq.times, case.times, atol=1e-6)


def test_nclt_session_with_both_formats_is_ambiguous(tmp_path, capsys):
    path, _, _ = _nclt_hits(tmp_path)
    session = path.parent
    with pytest.raises(LirisError, match="ambiguous.*nclt.*nclt-hits.*--dataset"):
        open_sequence(session)
    assert _quiet_open(session, dataset="nclt-hits").dataset == "nclt-hits"
    code, out, err = run_cli(["gt", session, "--json"], capsys)
    assert_one_line_error(code, err, "ambiguous", "--dataset")


def test_oxford_planar_4xN_not_Nx4(tmp_path):
    path, case, _ = _oxford(tmp_path)
    seq = _quiet_open(path)
    _check_scans(seq, case, [to_liris_points(p, OXFORD_TO_LIRIS) for p in case.scans])
    interleaved = np.fromfile(seq.scan_paths[0], dtype="<f4").reshape(-1, 4)[:, :3]
    assert not np.allclose(interleaved, case.scans[0], atol=1.0)  # the wrong reading differs
    np.testing.assert_allclose(seq.poses, to_liris_poses(case.poses, OXFORD_TO_LIRIS), atol=1e-8)


def test_oxford_extrinsics_folder_overrides_the_sdk_values(tmp_path):
    from dataset_writers import write_oxford_ins

    path, case, _ = _oxford(tmp_path)
    run = path.parent
    ins, lidar = (0.1, 0.2, 0.3, 0.01, 0.02, 0.03), (-0.5, 0.1, 0.2, 0.0, 0.0, 3.1)
    (run / "extrinsics").mkdir()
    (run / "extrinsics" / "ins.txt").write_text(" ".join(map(str, ins)) + "\n")
    (run / "extrinsics" / "velodyne_left.txt").write_text(" ".join(map(str, lidar)) + "\n")
    write_oxford_ins(run, case, np.linalg.inv(xyzrpy(*ins)) @ xyzrpy(*lidar))
    seq = _quiet_open(run)
    np.testing.assert_allclose(seq.poses, to_liris_poses(case.poses, OXFORD_TO_LIRIS), atol=1e-8)
    assert "extrinsics/ins.txt" in seq.pose_source


def test_oxford_raw_png_decoded_as_the_sdk(tmp_path):
    case = loop_case(5)
    run, raws = write_oxford_png(tmp_path, case)
    seq = _quiet_open(run)
    for k, raw in enumerate(raws):
        points, intensity = oxford_raw_expected(*raw)
        scan = seq.scan(k)
        # both in beam-major order: beam 0's valid firings, then beam 1's ...
        np.testing.assert_allclose(scan.points, to_liris_points(points, OXFORD_TO_LIRIS),
                                   atol=1e-4)
        np.testing.assert_allclose(scan.intensity, intensity)
        assert len(scan.points) == int((raw[0] * 0.002 > 1.0).sum())  # the 0.8 m return dropped
    np.testing.assert_allclose(seq.poses, to_liris_poses(case.poses, OXFORD_TO_LIRIS), atol=1e-8)


@pytest.mark.parametrize("sensor,size", [("Ouster", 26), ("Velodyne", 22), ("Avia", 19)])
def test_helipr_record_sizes(tmp_path, sensor, size):
    case = loop_case(6)
    folder = write_helipr(tmp_path, case, sensor)
    first = sorted(folder.iterdir())[0]
    assert first.stat().st_size == size * len(case.scans[0])
    seq = _quiet_open(folder)
    assert len(seq) == len(case.times) and len(seq.poses) == len(case.times)
    assert [len(seq.scan(k).points) for k in range(len(seq))] == [len(s) for s in case.scans]
    _check_scans(seq, case, intensity=sensor != "Avia")
    if sensor == "Avia":  # reflectivity (uint8) is the intensity
        assert np.array_equal(seq.scan(0).intensity,
                              np.clip(case.intensity[0], 0, 255).astype(np.uint8))
    np.testing.assert_allclose(seq.poses, case.poses, atol=1e-8)
    assert seq.sensor_preset == {"Ouster": "os2-128", "Velodyne": "vlp16", "Avia": "avia"}[sensor]


def test_helipr_aeva_switches_from_25_to_29_bytes_at_the_stamp(tmp_path):
    case = loop_case(6)
    stamps = [HELIPR_SWITCH - 2 * 10**8, HELIPR_SWITCH - 10**8, HELIPR_SWITCH,
              HELIPR_SWITCH + 10**8, HELIPR_SWITCH + 2 * 10**8]
    folder = write_helipr(tmp_path, case, "Aeva", stamps=stamps)
    sizes = [(folder / f"{s}.bin").stat().st_size // len(p) for s, p in
             zip(stamps, case.scans, strict=True)]
    assert sizes == [25, 25, 25, 29, 29]  # the switch stamp itself is still 25 bytes
    seq = _quiet_open(folder)
    assert len(seq) == 5 and len(seq.poses) == 5
    for k in range(5):
        scan = seq.scan(k)
        np.testing.assert_allclose(scan.points, case.scans[k], atol=POINT_ATOL)
        # 29-byte files carry intensity; 25-byte files fall back to reflectivity
        want = case.intensity[k] + (0.5 if sizes[k] == 25 else 0.0)
        np.testing.assert_allclose(scan.intensity, want, atol=1e-4)
    assert seq.sensor_preset is None


def test_helipr_finds_its_ground_truth_from_the_sensor_folder(tmp_path):
    case = loop_case(6)
    folder = write_helipr(tmp_path, case, "Aeva")
    gt = folder.parent.parent / "LiDAR_GT" / "global_Aeva_gt.txt"
    assert _quiet_open(folder, dataset="helipr").pose_source.startswith(str(gt))
    gt.unlink()
    with pytest.raises(LirisError, match="global_Aeva_gt.txt"):
        open_sequence(folder, dataset="helipr")


@pytest.mark.parametrize("maker", [_wild_v3, _wild_v12, _ncd, _boreas, _apollo])
def test_pose_and_points_of_the_text_pose_readers(tmp_path, maker):
    path, case, name = maker(tmp_path)
    seq = _quiet_open(path)
    np.testing.assert_allclose(seq.poses, case.poses, atol=1e-7)
    _check_scans(seq, case)


def test_apollo_pairs_by_index_and_counts_the_scan_without_a_row(tmp_path):
    path, case, _ = _apollo(tmp_path)
    with pytest.warns(LirisWarning, match="dropped 1 of 6 scans"):
        seq = open_sequence(path)
    assert list(seq.frame_ids) == [1, 2, 3, 4, 5] and seq.unmatched == 1


def test_nuscenes_keyframes_poses_and_scene_choice(tmp_path):
    root, case, _ = _nuscenes(tmp_path)
    with pytest.raises(LirisError, match="2 scenes.*--scene"):
        open_sequence(root)
    seq = open_sequence(root / "v1.0-mini", scene="scene-0061")
    assert len(seq) == len(case.times)  # the sweeps between keyframes are skipped
    assert all("samples/LIDAR_TOP" in str(p) for p in seq.scan_paths)
    np.testing.assert_allclose(seq.poses, case.poses, atol=1e-8)
    kept = [~((np.abs(p[:, 0]) < 1.0) & (np.abs(p[:, 1]) < 1.0)) for p in case.scans]
    for k, keep in enumerate(kept):
        np.testing.assert_allclose(seq.scan(k).points, case.scans[k][keep], atol=POINT_ATOL)
        np.testing.assert_allclose(seq.scan(k).intensity, case.intensity[k][keep], atol=1e-4)
    with pytest.raises(LirisError, match="--scene scene-9999"):
        open_sequence(root, scene="scene-9999")


def test_kitti360_sparse_poses_interpolated_by_frame(tmp_path):
    case = loop_case(13)
    drive, kept, expected = write_kitti360(tmp_path, case)
    with pytest.warns(LirisWarning, match="dropped 2 of 8 scans outside the posed frames 1..6"):
        seq = open_sequence(drive / "velodyne_points" / "data")
    assert list(seq.frame_ids) == list(kept)
    np.testing.assert_allclose(seq.poses, expected, atol=1e-9)
    np.testing.assert_allclose(seq.scan(0).points, case.scans[0], atol=POINT_ATOL)
    assert seq.times[1] - seq.times[0] == pytest.approx(0.1, abs=1e-6)


# --- selection, sensor, cache: as on KITTI ----------------------------------------------------


def test_frames_sensor_auto_and_cache_on_a_dataset(tmp_path, capsys):
    path, case, _ = _mulran(tmp_path)
    args = ["extract", path, "-d", "scan-context", "--cache-dir", tmp_path / "c", "-q",
            "--json", "--frames", "0:4", "--sensor", "auto"]
    code, out, err = run_cli(args, capsys)
    assert code == 0, err
    assert "--sensor auto: chose" in err
    first = json.loads(out)["results"][0]
    assert first["scans"] == 4 and first["from_cache"] is False
    code, out, err = run_cli(args, capsys)
    assert code == 0 and json.loads(out)["results"][0]["from_cache"] is True
    assert len(_quiet_open(path, frames="1:3")) == 2


def test_forced_dataset_and_option_errors(tmp_path, capsys):
    path, _, _ = _boreas(tmp_path)
    code, _, err = run_cli(["gt", path, "--dataset", "nosuch"], capsys)
    assert_one_line_error(code, err, "--dataset nosuch", "unknown dataset", "mulran")
    code, _, err = run_cli(["gt", path, "--dataset", "boreas", "--pose-format", "tum"], capsys)
    assert_one_line_error(code, err, "--pose-format", "not used for dataset boreas")
    code, _, err = run_cli(["gt", path, "--dataset", "mulran"], capsys)
    assert_one_line_error(code, err, "Ouster")


def test_unknown_folder_names_what_was_looked_for(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code, _, err = run_cli(["gt", tmp_path / "empty"], capsys)
    assert_one_line_error(code, err, "not a known dataset layout", "mulran: Ouster/",
                          "helipr:", "--dataset")


def test_liris_datasets_lists_every_reader(capsys):
    code, out, err = run_cli(["datasets"], capsys)
    assert code == 0, err
    for spec in DATASETS.values():
        assert spec.name in out and spec.layout in out
    code, out, _ = run_cli(["datasets", "--json"], capsys)
    listed = json.loads(out)
    assert [d["name"] for d in listed] == list(DATASETS)
    assert {d["name"]: d["sensor"] for d in listed}["mulran"] == "os1-64-gen1"


# --- truncated and malformed files: one line, exit 2 ---------------------------------------------


def assert_one_error_line(code: int, err: str, *fragments: str) -> None:
    """Exit 2 and one error line (warning lines, e.g. a dropped scan, may precede it)."""
    errors = "\n".join(ln for ln in err.splitlines() if not ln.startswith("liris: warning:"))
    assert_one_line_error(code, errors, *fragments)


def _truncate(path: Path, cut: int = 1) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:-cut])


@pytest.mark.parametrize("name,fragments", [
    ("helipr-Aeva", ["25-byte record", "up to stamp"]),
    ("helipr-Ouster", ["26-byte record"]),
    ("helipr-Velodyne", ["22-byte record"]),
    ("helipr-Avia", ["19-byte record"]),
    ("nclt", ["8-byte record", "u16 x"]),
    ("boreas", ["24-byte record"]),
    ("nuscenes", ["20-byte record"]),
    ("oxford", ["multiple of 16", "planar"]),
    ("mulran", ["multiple of 16"]),
])
def test_truncated_record_file_is_one_line_exit_2(tmp_path, capsys, name, fragments):
    path, case, dataset = MAKERS[name](tmp_path)
    seq = _quiet_open(path, **({"scene": "scene-0061"} if dataset == "nuscenes" else {}))
    victim = seq.scan_paths[-1]
    _truncate(victim)
    code, _, err = run_cli(["extract", path, "-d", "scan-context", "--cache-dir",
                            tmp_path / "c", "-q", *EXTRA.get(name, [])], capsys)
    assert_one_error_line(code, err, str(victim), *fragments)


def test_truncated_hits_packet_names_the_offset(tmp_path, capsys):
    path, _, _ = _nclt_hits(tmp_path)
    _truncate(path, 3)
    code, _, err = run_cli(["gt", path], capsys)
    assert_one_error_line(code, err, str(path), "cut short", "24-byte packet header")
    data = bytearray(path.read_bytes())
    data[0] = 0
    path.write_bytes(bytes(data))
    with pytest.raises(LirisError, match="no magic"):
        open_sequence(path)


def test_malformed_pose_rows_name_the_line(tmp_path, capsys):
    path, _, _ = _mulran(tmp_path)
    pose = path / "global_pose.csv"
    lines = pose.read_text().splitlines()
    lines[2] = "1,2,3"
    pose.write_text("\n".join(lines) + "\n")
    code, _, err = run_cli(["gt", path], capsys)
    assert_one_error_line(code, err, f"{pose}:3", "expected 13")


def test_oxford_png_with_wrong_rows_is_an_error(tmp_path):
    from PIL import Image

    run, _ = write_oxford_png(tmp_path, loop_case(5))
    victim = sorted((run / "velodyne_left").iterdir())[0]
    Image.fromarray(np.zeros((100, 8), np.uint8), mode="L").save(victim)
    seq = _quiet_open(run)
    with pytest.raises(LirisError, match="100 rows, expected 106"):
        seq.scan(0)


def test_nclt_ground_truth_searched_in_the_documented_places(tmp_path):
    path, _, _ = _nclt(tmp_path)
    (tmp_path / "ground_truth" / "groundtruth_2012-01-08.csv").rename(
        path / "groundtruth_2012-01-08.csv")
    assert _quiet_open(path).pose_source.startswith(str(path / "groundtruth_2012-01-08.csv"))
    (path / "groundtruth_2012-01-08.csv").unlink()
    with pytest.raises(LirisError, match="groundtruth_2012-01-08.csv"):
        open_sequence(path)
    rows(tmp_path / "gt.csv", [["1", 0, 0, 0, 0, 0, 0]])
    with pytest.raises(LirisError, match="no scan has a pose"):
        open_sequence(path, poses=tmp_path / "gt.csv")


# --- processes and replays ------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["helipr-Aeva", "nclt-hits"])
def test_sequences_pickle_for_worker_processes(tmp_path, name):
    import pickle

    path, _, _ = MAKERS[name](tmp_path)
    seq = _quiet_open(path)
    back = pickle.loads(pickle.dumps(seq))
    assert back.fingerprint() == seq.fingerprint()
    np.testing.assert_array_equal(back.scan(2).points, seq.scan(2).points)


def test_forced_helipr_sensor_folder_is_recorded_and_replayed(tmp_path, capsys):
    import yaml

    path, _, _ = _helipr("Aeva")(tmp_path)
    args = ["eval", path, "--dataset", "helipr", "-d", "scan-context", "--protocol", "1",
            "--exclude", "2", "--pose-frame", "lidar", "--cache-dir", tmp_path / "c", "-q"]
    code, _, err = run_cli([*args, "--out", tmp_path / "run"], capsys)
    assert code == 0, err
    config = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
    assert config["sequence"]["reader_options"]["dataset"] == "helipr"
    code, _, err = run_cli(["eval", "--config", tmp_path / "run", "--out", tmp_path / "again",
                            "-q"], capsys)
    assert code == 0, err
    first, again = (json.loads((tmp_path / r / "metrics.json").read_text())["results"]
                    for r in ("run", "again"))
    assert first[0]["ap"] == again[0]["ap"] == pytest.approx(1.0)
