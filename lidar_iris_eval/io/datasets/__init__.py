"""The dataset registry: one small reader module per dataset, detected from the folder.

Each :class:`DatasetSpec` says what layout its reader expects, which frame the
dataset's poses are in, what liris converts, and which ``--sensor`` preset
fits its LiDAR. :func:`find_dataset` picks the spec for a path: the one named
by ``dataset=`` (``--dataset``), else the one specific dataset whose layout
matches, else the generic readers (GOSMatch objects, KITTI layout, ROS bag,
folder of scans) in that order. Two specific matches, or none at all, are one
error line naming what was looked for.

Readers are imported on first use, so listing or detecting costs no imports.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from lidar_iris_eval.errors import LirisError


@dataclass(frozen=True)
class DatasetSpec:
    """One registered dataset (or generic format).

    Attributes
    ----------
    name : the ``--dataset`` name.
    title : the dataset's own name.
    layout : the path to give and what must be around it.
    pose_frame : the frame of the dataset's poses as distributed.
    converts : what liris does to them (extrinsic, time matching, interpolation).
    sensor : the ``--sensor`` preset of its LiDAR, or None where liris has none.
    looks_for : the short cue detection tests, for error messages.
    detect : ``detect(path) -> bool``.
    opener : ``"module:function"`` under this package, called as
        ``opener(path, poses=..., calib=..., **options)``.
    generic : detected only when no specific dataset matches.
    frame : the frame of the scans as stored, and what liris turns it into:
        every reader returns z-up scans (x forward, y left, z up, as KITTI).
    intensity : what the reader returns as a scan's intensity (field, unit, range).
    """

    name: str
    title: str
    layout: str
    pose_frame: str
    converts: str
    sensor: str | None
    looks_for: str
    detect: Callable[[Path], bool]
    opener: str
    generic: bool = False
    frame: str = ""
    intensity: str = ""

    def open(self, path: Path, **options):
        """Open ``path`` with this dataset's reader.

        ``opener`` names a module of this package (``"mulran:open_mulran"``), or,
        for a reader outside it, any importable module (``"liris_mine.reader:open"``).
        """
        module_name, func_name = self.opener.split(":")
        if (Path(__file__).parent / f"{module_name}.py").is_file():
            module_name = f"lidar_iris_eval.io.datasets.{module_name}"
        module = importlib.import_module(module_name)
        return getattr(module, func_name)(Path(path), **options)


# --- detection cues (cheap: a few stat calls each) ----------------------------


def _is_dir(path: Path, *parts: str) -> bool:
    return path.joinpath(*parts).is_dir()


def _is_file(path: Path, *parts: str) -> bool:
    return path.joinpath(*parts).is_file()


_KITTI360_DRIVE = re.compile(r"^\d{4}_\d{2}_\d{2}_drive_\d{4}_sync$")
HELIPR_SENSORS = ("Ouster", "Velodyne", "Aeva", "Avia")


def kitti360_drive(path: Path) -> Path | None:
    """The ``<date>_drive_<NNNN>_sync`` folder of a KITTI-360 path, or None."""
    for candidate in (path, path.parent, path.parent.parent):
        if _KITTI360_DRIVE.match(candidate.name) and _is_dir(candidate, "velodyne_points"):
            return candidate
    return None


def mulran_sequence(path: Path) -> Path | None:
    """The MulRan sequence folder (holding ``Ouster/``) of a path, or None."""
    if path.name == "Ouster" and _is_file(path.parent, "global_pose.csv"):
        return path.parent
    if _is_dir(path, "Ouster") and _is_file(path, "global_pose.csv"):
        return path
    return None


def nclt_session(path: Path) -> Path | None:
    """The NCLT ``<date>`` folder when ``path`` is it (with velodyne_sync/) or velodyne_sync/."""
    if path.name == "velodyne_sync" and path.is_dir():
        return path.parent
    if _is_dir(path, "velodyne_sync"):
        return path
    return None


def nclt_hits_file(path: Path) -> Path | None:
    """``velodyne_hits.bin`` itself, or inside ``path``."""
    if path.name == "velodyne_hits.bin" and path.is_file():
        return path
    if _is_file(path, "velodyne_hits.bin"):
        return path / "velodyne_hits.bin"
    return None


def oxford_scan_dir(path: Path) -> Path | None:
    """``<run>/velodyne_left`` (or ``_right``) of an Oxford Radar RobotCar path, or None."""
    if path.name in ("velodyne_left", "velodyne_right") and path.is_dir():
        return path
    for side in ("velodyne_left", "velodyne_right"):
        if _is_dir(path, side) and _is_file(path, f"{side}.timestamps"):
            return path / side
    return None


def _oxford_has(path: Path, suffix: str) -> bool:
    folder = oxford_scan_dir(path)
    return folder is not None and any(p.suffix == suffix for p in folder.iterdir())


def helipr_sensor(path: Path) -> str | None:
    """The HeLiPR sensor name when ``path`` is ``<seq>/LiDAR/<Sensor>``, else None."""
    if path.name in HELIPR_SENSORS and path.parent.name == "LiDAR" and path.is_dir():
        return path.name
    return None


def _wild_v3(path: Path) -> bool:
    return _is_file(path, "submap_poses.csv") or (
        path.name == "Clouds_downsampled" and _is_file(path.parent, "submap_poses.csv"))


def _wild_v12(path: Path) -> bool:
    return _is_file(path, "poses_aligned.csv") or (
        path.name == "Clouds" and _is_file(path.parent, "poses_aligned.csv"))


def _newer_college(path: Path) -> bool:
    return _is_file(path, "ground_truth", "registered_poses.csv") or (
        path.name == "ouster_scan" and path.parent.name == "raw_format")


def nuscenes_tables(path: Path) -> Path | None:
    """The ``v1.0-*`` folder of JSON tables under a nuScenes data root, or None."""
    if _is_file(path, "sample_data.json") and _is_file(path, "ego_pose.json"):
        return path
    if not path.is_dir():
        return None
    for child in sorted(path.glob("v1.0-*")):
        if _is_file(child, "sample_data.json"):
            return child
    return None


def _boreas(path: Path) -> bool:
    return _is_file(path, "applanix", "lidar_poses.csv") or (
        path.name == "lidar" and _is_file(path.parent, "applanix", "lidar_poses.csv"))


def _apollo(path: Path) -> bool:
    return _is_file(path, "poses", "gt_poses.txt") or (
        path.name == "pcds" and _is_file(path.parent, "poses", "gt_poses.txt"))


def _kitti(path: Path) -> bool:
    from lidar_iris_eval.io.kitti import is_kitti_layout

    return is_kitti_layout(path)


def _objects(path: Path) -> bool:
    from lidar_iris_eval.io.objects import is_objects_layout

    return is_objects_layout(path)


def _rosbag(path: Path) -> bool:
    if path.is_file():
        return path.suffix in (".bag", ".db3", ".mcap")
    return _is_file(path, "metadata.yaml")


def _folder(path: Path) -> bool:
    from lidar_iris_eval.io.sequence import SCAN_READERS

    return path.is_dir() and any(
        p.suffix.lower() in SCAN_READERS and p.is_file() for p in path.iterdir())


DATASETS: dict[str, DatasetSpec] = {s.name: s for s in (
    DatasetSpec(
        "kitti360", "KITTI-360",
        "KITTI-360/data_3d_raw/<date>_drive_<NNNN>_sync (velodyne_points/data/%010d.bin); "
        "data_poses/<drive>/poses.txt and calibration/ beside data_3d_raw",
        "IMU/GPS → world, only for some frames (frame index + 3×4)",
        "interpolated to every LiDAR frame by frame index (slerp + linear; frames outside the "
        "posed range dropped), then T · cam0_to_pose · inv(cam_to_velo)",
        "hdl64", "a *_drive_NNNN_sync folder with velodyne_points/",
        lambda p: kitti360_drive(p) is not None, "kitti360:open_kitti360",
        frame="Velodyne HDL-64E, x forward, y left, z up: kept",
        intensity="the file's reflectance (f32, 0..1), as stored"),
    DatasetSpec(
        "mulran", "MulRan",
        "<Seq>/Ouster/<ns>.bin + <Seq>/global_pose.csv (open <Seq> or <Seq>/Ouster)",
        "vehicle base frame, ns stamps, more rows than scans",
        "each scan gets the pose at its stamp (interpolated, named tolerance); "
        "T_base · T_base_ouster (calib_base2ouster.txt)",
        "os1-64-gen1", "Ouster/ beside global_pose.csv",
        lambda p: mulran_sequence(p) is not None, "mulran:open_mulran",
        frame=("Ouster OS1-64, z up: kept (its x points backwards on the car, base → Ouster yaw "
               "179.67°; not turned)"),
        intensity="the file's fourth f32 (Ouster intensity, raw counts), as stored"),
    DatasetSpec(
        "nclt", "NCLT (velodyne_sync)",
        "<date>/velodyne_sync/<utime>.bin; ground_truth/groundtruth_<date>.csv in <date>, "
        "beside it or in ../ground_truth",
        "body frame (z down), utime µs, x y z roll pitch yaw",
        "uint16 coordinates (·0.005 − 100 m, never int16); pose at each scan stamp; "
        "T_body · T_body_velodyne",
        "hdl32", "velodyne_sync/",
        lambda p: nclt_session(p) is not None, "nclt:open_nclt_sync",
        frame=("Velodyne frame x left, y forward, z down → turned to x forward, y left, z up (x' "
               "= y, y' = x, z' = −z); poses turned alike"),
        intensity="the u8 intensity byte (0..255)"),
    DatasetSpec(
        "nclt-hits", "NCLT (raw velodyne_hits.bin)",
        "<date>/velodyne_hits.bin (open the file or <date>); ground truth as for nclt",
        "body frame (z down), utime µs",
        "packets split into revolutions at the ±180° azimuth wrap; as nclt otherwise",
        "hdl32", "velodyne_hits.bin",
        lambda p: nclt_hits_file(p) is not None, "nclt:open_nclt_hits",
        frame="as nclt: turned from x left, y forward, z down to x forward, y left, z up",
        intensity="the u8 intensity byte (0..255)"),
    DatasetSpec(
        "oxford", "Oxford Radar RobotCar (velodyne .bin)",
        "<run>/velodyne_left/<ts>.bin + <run>/velodyne_left.timestamps + <run>/gps/ins.csv "
        "(extrinsics/ in <run> or its parent, else the SDK's values)",
        "INS (northing, easting, down, roll, pitch, yaw), µs",
        "planar 4×N float32 (never N×4); INS pose at each scan stamp; "
        "T_ins · inv(T_stereo_ins) · T_stereo_velodyne",
        "hdl32", "velodyne_left|right/ with .bin scans",
        lambda p: _oxford_has(p, ".bin"), "oxford:open_oxford_bin",
        frame=("SDK Velodyne frame x backward, y left, z down (extrinsic yaw ≈ π from the "
               "x-forward, y-right, z-down stereo frame) → turned by π about y (x' = −x, z' = −z)"
               " to x forward, y left, z up; poses turned alike"),
        intensity="the fourth planar f32 row (HDL-32E intensity, 0..255), as stored"),
    DatasetSpec(
        "oxford-raw", "Oxford Radar RobotCar (raw velodyne .png)",
        "<run>/velodyne_left/<ts>.png; timestamps, INS and extrinsics as for oxford",
        "INS, as for oxford",
        "rows 0-31 intensity, 32-95 ranges (uint16 · 2 mm), 96-97 azimuth; fixed HDL-32E "
        "elevations (SDK); returns under 1 m dropped; poses as for oxford",
        "hdl32", "velodyne_left|right/ with .png scans",
        lambda p: _oxford_has(p, ".png"), "oxford:open_oxford_png",
        frame="as oxford: the SDK's points (z down) turned by π about y",
        intensity="rows 0-31, u8 (0..255)"),
    DatasetSpec(
        "helipr", "HeLiPR",
        "<seq>/LiDAR/{Ouster,Velodyne,Aeva,Avia} (open the sensor folder); "
        "<seq>/LiDAR_GT/global_<Sensor>_gt.txt",
        "LiDAR frame of that sensor, t (ns) x y z qx qy qz qw",
        "packed records per sensor (26/22/25-or-29/19 B; Aeva 29 B after stamp "
        "1691936557946849179); pose at each scan stamp",
        "os2-128 (Ouster), vlp16 (Velodyne), avia (Avia), none (Aeva)",
        "a sensor folder under LiDAR/",
        lambda p: helipr_sensor(p) is not None, "helipr:open_helipr",
        frame="each sensor's own frame, z up: kept",
        intensity=("Ouster, Velodyne: the f32 intensity field as stored; Avia: u8 reflectivity "
                   "(0..255); Aeva 25 B (up to stamp 1691936557946849179): the f32 reflectivity "
                   "field; Aeva 29 B: the trailing f32 intensity as stored, negative and dB-like "
                   "(about −73..−27 on real files)")),
    DatasetSpec(
        "wild-places", "Wild-Places v1/v2",
        "<seq>/Clouds/<time>.pcd + <seq>/poses_aligned.csv",
        "submap poses (timestamp,x,y,z,qx,qy,qz,qw); clouds are accumulated submaps",
        "pose matched to each submap's stamp; no extrinsic",
        "vlp16", "poses_aligned.csv",
        _wild_v12, "wildplaces:open_wild_v12",
        frame="submap frame, z up: kept",
        intensity="the PCD's intensity field as stored, else none"),
    DatasetSpec(
        "wild-places-v3", "Wild-Places v3",
        "<seq>/Clouds_downsampled/<time>.bin + <seq>/submap_poses.csv",
        "submap poses (%time,x,y,z,qx,qy,qz,qw); clouds are accumulated submaps",
        "pose matched to each submap's stamp; no extrinsic",
        "vlp16", "submap_poses.csv",
        _wild_v3, "wildplaces:open_wild_v3",
        frame="submap frame, z up: kept",
        intensity="the file's fourth f32, as stored"),
    DatasetSpec(
        "newer-college", "Newer College 2020",
        "<root>/raw_format/ouster_scan/cloud_<sec>_<nsec>.pcd + "
        "<root>/ground_truth/registered_poses.csv",
        "base frame, sec,nsec,x,y,z,qx,qy,qz,qw",
        "pose at each scan stamp; T_base · T_CL (q = 0, 0, 0.924, 0.383; "
        "t = −0.084, −0.025, 0.050)",
        "os1-64-gen1", "ground_truth/registered_poses.csv",
        _newer_college, "newer_college:open_newer_college",
        frame="Ouster OS1-64, z up: kept",
        intensity="the PCD's intensity field as stored, else none"),
    DatasetSpec(
        "nuscenes", "nuScenes",
        "<dataroot> with v1.0-*/ JSON tables and samples/LIDAR_TOP/*.pcd.bin "
        "(one scene; --scene NAME when there are several)",
        "ego_pose (global) × calibrated_sensor (LIDAR_TOP → ego), µs",
        "keyframes of LIDAR_TOP walked through the next tokens; "
        "pose = ego_pose · calibrated_sensor (quaternions w, x, y, z)",
        "hdl32", "v1.0-*/sample_data.json",
        lambda p: nuscenes_tables(p) is not None, "nuscenes:open_nuscenes",
        frame=("LIDAR_TOP frame (x right, y forward, z up on the car): kept; ego returns dropped "
               "as the devkit does (|x| < 1.0 m and |y| < 1.0 m, remove_close)"),
        intensity="the record's fourth f32 (HDL-32E intensity, 0..255), as stored"),
    DatasetSpec(
        "boreas", "Boreas",
        "<seq>/lidar/<µs>.bin + <seq>/applanix/lidar_poses.csv",
        "LiDAR frame in ENU (GPSTime µs, x, y, z, …, roll, pitch, yaw)",
        "float32 × 6 records; pyboreas rotation convention; pose at each scan stamp",
        None, "applanix/lidar_poses.csv",
        _boreas, "boreas:open_boreas",
        frame="Velodyne Alpha Prime frame, z up: kept",
        intensity="the record's fourth f32, as stored"),
    DatasetSpec(
        "apollo", "Apollo-SouthBay",
        "<route>/<date>/pcds/<n>.pcd + <route>/<date>/poses/gt_poses.txt",
        "LiDAR frame (index, time, x, y, z, qx, qy, qz, qw)",
        "pose by the index column = pcd file number; no extrinsic",
        "hdl64", "poses/gt_poses.txt",
        _apollo, "apollo:open_apollo",
        frame="LiDAR frame, z up: kept",
        intensity="the PCD's intensity field as stored, else none"),
    DatasetSpec(
        "objects", "GOSMatch object layout",
        "a folder with bow.txt and centroids/ (the GOSMatch authors' files)",
        "KITTI camera frame", "inv(Tr) · T · Tr", None, "bow.txt + centroids/",
        _objects, "generic:open_objects_layout", generic=True,
        frame="KITTI Velodyne frame (object centroids): kept",
        intensity="none"),
    DatasetSpec(
        "kitti", "KITTI odometry / SemanticKITTI (and liris simulate)",
        "sequences/NN with velodyne/%06d.bin, calib.txt, poses.txt or ../../poses/NN.txt",
        "left camera frame", "inv(Tr) · T · Tr", "hdl64", "velodyne/",
        _kitti, "generic:open_kitti_layout", generic=True,
        frame="Velodyne, x forward, y left, z up (the reference): kept",
        intensity="the file's reflectance (f32, 0..1 on KITTI), as stored"),
    DatasetSpec(
        "rosbag", "ROS 1 / ROS 2 bag",
        "a .bag, .db3 or .mcap file, or a ROS 2 bag folder (metadata.yaml)",
        "as published (odometry / pose topic or a pose file)",
        "pose at each message stamp (see docs)", None, ".bag/.db3/.mcap or metadata.yaml",
        _rosbag, "generic:open_rosbag_file", generic=True,
        frame="the cloud's frame as published: kept (not turned)",
        intensity="the message's intensity field as published, else none"),
    DatasetSpec(
        "folder", "folder of scans",
        "a folder of .bin/.npy/.pcd scans with poses.txt, poses_tum.txt or *.tum",
        "KITTI camera frame (calib.txt) or LiDAR (--lidar-frame-poses)",
        "inv(Tr) · T · Tr, or none; TUM poses matched by time", None,
        ".bin/.npy/.pcd scan files", _folder, "generic:open_scan_folder", generic=True,
        frame="as stored: kept (not turned)",
        intensity="the file's fourth column / intensity field as stored, else none"),
)}


def _plugin_spec(plugin) -> DatasetSpec:
    """An external reader's spec, named by its entry; one LirisError if it is broken."""
    import dataclasses

    spec = plugin.load()
    if not isinstance(spec, DatasetSpec):
        raise LirisError(plugin.label, "is not a lidar_iris_eval.io.datasets.DatasetSpec")
    return dataclasses.replace(spec, name=plugin.name)


def all_datasets(strict: bool = True) -> dict[str, DatasetSpec]:
    """:data:`DATASETS` and the external readers (entry points ``liris.datasets``,
    ``LIRIS_DATASETS``; :mod:`lidar_iris_eval.plugins`), specific readers first and
    the generic ones last, so an external layout is detected before a folder of scans.

    ``strict=False`` (``liris datasets``) leaves out, with a warning, a reader
    that cannot be loaded; otherwise it is one error naming it.
    """
    from lidar_iris_eval.errors import warn
    from lidar_iris_eval.plugins import plugins

    external = {}
    try:
        found = plugins("datasets", reserved=set(DATASETS))
    except LirisError as err:
        if strict:
            raise
        warn(err.source, err.problem)
        found = []
    for plugin in found:
        try:
            external[plugin.name] = _plugin_spec(plugin)
        except LirisError as err:
            if strict:
                raise
            warn(err.source, f"{err.problem}; not listed")
    if not external:
        return dict(DATASETS)
    specific = {n: s for n, s in DATASETS.items() if not s.generic}
    generic = {n: s for n, s in DATASETS.items() if s.generic}
    return {**specific, **{n: s for n, s in external.items() if not s.generic},
            **{n: s for n, s in external.items() if s.generic}, **generic}


def dataset_names() -> list[str]:
    """Every registered name, specific datasets first."""
    return list(all_datasets())


def get_dataset(name: str) -> DatasetSpec:
    """The spec registered as ``name`` (one error listing the names otherwise)."""
    datasets = all_datasets()
    spec = datasets.get(str(name).lower(), datasets.get(str(name)))
    if spec is None:
        raise LirisError(f"--dataset {name}",
                         f"unknown dataset; choose from {', '.join(datasets)} (liris datasets)")
    return spec


def find_dataset(path: Path, dataset: str | None = None) -> DatasetSpec:
    """The spec to open ``path`` with: forced by ``dataset``, else detected."""
    path = Path(path)
    if dataset is not None:
        return get_dataset(dataset)
    datasets = all_datasets()
    specific = [s for s in datasets.values() if not s.generic and s.detect(path)]
    if len(specific) > 1:
        names = " and ".join(f"{s.name} ({s.looks_for})" for s in specific)
        raise LirisError(path, f"ambiguous dataset layout: {names} both match; "
                               "choose one with --dataset NAME")
    if specific:
        return specific[0]
    for spec in datasets.values():
        if spec.generic and spec.detect(path):
            return spec
    cues = "; ".join(f"{s.name}: {s.looks_for}" for s in datasets.values())
    raise LirisError(path, f"not a known dataset layout or folder of scans; looked for {cues} "
                           "(see liris datasets, or force one with --dataset NAME)")


__all__ = ["DATASETS", "DatasetSpec", "all_datasets", "dataset_names", "find_dataset",
           "get_dataset"]
