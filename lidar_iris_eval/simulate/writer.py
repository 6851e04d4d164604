"""Writing a simulated sequence in the KITTI odometry layout.

``velodyne/NNNNNN.bin`` (float32 x y z intensity), ``labels/NNNNNN.label``
(SemanticKITTI uint32: class | instance << 16), ``object_ids/NNNNNN.npy``
(uint32 per point: the physical object hit, 0 for the ground, the same id in
every scan; SemanticKITTI gives "stuff" such as buildings instance 0, so this
sits beside the labels instead of changing them), ``poses.txt`` (camera frame,
first pose identity), ``times.txt``, ``calib.txt`` (``P0:``..``P3:`` and
``Tr:``) and ``manifest.json``. Every file is written to a temporary name in
the same folder and moved into place with :func:`os.replace`, so an
interrupted run never leaves a half-written file under a final name.
"""

from __future__ import annotations

import io
import json
import os
import re
import shutil
from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, check_writable_dir, os_error
from lidar_iris_eval.ownership import list_files


def default_tr() -> np.ndarray:
    """A KITTI-like LiDAR-to-camera transform (4x4).

    Camera axes are x right, y down, z forward; the LiDAR's are x forward,
    y left, z up. A small misalignment (a few tenths of a degree) and a lever
    arm of about 0.3 m make it non-trivial, like KITTI's, so readers must apply
    ``T_lidar = inv(Tr) T_cam Tr`` to recover the LiDAR trajectory.
    """
    axes = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    ax, ay, az = np.deg2rad([0.35, -0.25, 0.45])
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    tr = np.eye(4)
    tr[:3, :3] = rx @ ry @ rz @ axes
    tr[:3, 3] = [0.03, -0.07, -0.28]
    return tr


def read_tr(path: str | os.PathLike) -> np.ndarray:
    """The ``Tr:`` (or ``Tr_velo_to_cam:``) line of a KITTI calib file as 4x4."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise LirisError(path, f"cannot read calib ({err.strerror})") from None
    for line in text.splitlines():
        key, _, rest = line.partition(":")
        if key.strip() in ("Tr", "Tr_velo_to_cam"):
            try:
                vals = np.array([float(v) for v in rest.split()])
            except ValueError:
                raise LirisError(path, f"bad number in {key.strip()} line") from None
            if len(vals) != 12:
                raise LirisError(path, f"{key.strip()} needs 12 numbers, found {len(vals)}")
            tr = np.eye(4)
            tr[:3, :] = vals.reshape(3, 4)
            return tr
    raise LirisError(path, "no Tr: line (KITTI calib format)")


def _fmt_row(values) -> str:
    return " ".join(f"{v:.12e}" for v in values)


def calib_text(tr: np.ndarray) -> str:
    """KITTI ``calib.txt`` content: four pinhole projections and ``Tr``."""
    f, cx, cy = 718.856, 607.1928, 185.2157
    lines = []
    for k, tx in enumerate((0.0, -0.537, 0.06, -0.475)):
        p = np.array([[f, 0, cx, f * tx], [0, f, cy, 0], [0, 0, 1, 0]])
        lines.append(f"P{k}: " + _fmt_row(p.ravel()))
    lines.append("Tr: " + _fmt_row(tr[:3, :].ravel()))
    return "\n".join(lines) + "\n"


def poses_text(poses: np.ndarray) -> str:
    """KITTI pose lines (row-major 3x4, 12 numbers each)."""
    return "".join(" ".join(f"{v:.9e}" for v in p[:3, :].ravel()) + "\n" for p in poses)


def times_text(n: int, dt: float = 0.1) -> str:
    return "".join(f"{i * dt:.6e}\n" for i in range(n))


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file and :func:`os.replace`."""
    from lidar_iris_eval.atomic import atomic_write as write

    write(path, data, what="simulated file")


def check_out_dir(out_dir: Path, overwrite: bool, sessions: bool = False) -> None:
    """Refuse a file, or a non-empty folder without ``overwrite``; creates nothing.

    With ``overwrite``, only a sequence ``liris simulate`` wrote (or, with
    ``sessions``, a folder of simulated sessions) holding nothing else is
    replaced (see :func:`check_simulation_replaceable`).
    """
    if out_dir.is_symlink() and overwrite:
        raise LirisError(out_dir, "OUT_DIR is a symbolic link; --overwrite does not replace links")
    if out_dir.exists() and not out_dir.is_dir():
        raise LirisError(out_dir, "exists and is not a directory")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        if not overwrite:
            raise LirisError(out_dir, "directory is not empty (use --overwrite to replace it)")
        check_simulation_replaceable(out_dir, sessions)
    check_writable_dir(out_dir.parent if str(out_dir.parent) else Path("."),
                       "folder for the simulated sequence")


#: what a finished simulation consists of; manifest.json is moved last (the completion mark)
PUBLISHED = ("velodyne", "labels", "object_ids", "poses.txt", "times.txt", "calib.txt",
             "manifest.json")


#: the files of a simulated sequence, relative to its folder
_SIMULATED_FILE = re.compile(r"(poses\.txt|times\.txt|calib\.txt|manifest\.json"
                             r"|velodyne/\d+\.bin|labels/\d+\.label|object_ids/\d+\.npy)")


def check_simulation_replaceable(out_dir: Path, sessions: bool = False) -> None:
    """Raise :class:`LirisError` unless ``--overwrite`` may replace the non-empty ``out_dir``.

    ``--overwrite`` replaces a simulated sequence, never a real one or a
    folder holding anything else: the folder's ``manifest.json`` must name
    ``liris simulate`` as its generator and every file must be one a
    simulation writes. A sessions folder (``sessions``) must hold its
    ``sessions.json`` and ``session<k>`` folders that each pass that check.
    """
    if sessions:
        if not (out_dir / "sessions.json").is_file():
            raise LirisError(out_dir, "not a folder of simulated sessions (no sessions.json); "
                                      "--overwrite only replaces what liris simulate wrote")
        for entry in sorted(out_dir.iterdir()):
            if entry.name == "sessions.json":
                continue
            if not re.fullmatch(r"session\d+", entry.name) or entry.is_symlink() \
                    or not entry.is_dir():
                raise LirisError(out_dir, f"holds {entry.name}, which liris simulate did not "
                                          "write; not replaced")
            check_simulation_replaceable(entry)
        return
    if not _written_by_simulate(out_dir / "manifest.json"):
        raise LirisError(out_dir, "not a sequence liris simulate wrote (no manifest.json "
                                  "naming it): --overwrite only replaces simulated sequences")
    for rel in list_files(out_dir):
        if not _SIMULATED_FILE.fullmatch(rel) or (out_dir / rel).is_symlink():
            raise LirisError(out_dir, f"holds {rel}, which liris simulate did not write; "
                                      "not replaced (move it away or choose another OUT_DIR)")


def _written_by_simulate(manifest: Path) -> bool:
    try:
        data = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return (isinstance(data, dict) and isinstance(data.get("generator"), str)
            and data["generator"].startswith("liris simulate"))


def publish(work: Path, out_dir: Path) -> None:
    """Move the complete sequence built in ``work`` to ``out_dir``.

    An absent or empty ``out_dir`` is replaced in one rename. A non-empty one
    (``--overwrite``) loses its ``manifest.json`` first, so until the last
    rename it is visibly unfinished; each part is then swapped in whole.
    """
    try:
        if not out_dir.exists() or (out_dir.is_dir() and not any(out_dir.iterdir())):
            os.replace(work, out_dir)
            return
        (out_dir / "manifest.json").unlink(missing_ok=True)
        for name in PUBLISHED:
            new, target = work / name, out_dir / name
            if not new.exists():
                continue
            if target.is_dir():
                aside = out_dir / f".{name}.old-{os.getpid()}"
                os.replace(target, aside)
                os.replace(new, target)
                shutil.rmtree(aside, ignore_errors=True)
            else:
                os.replace(new, target)
    except OSError as err:
        raise os_error(err, out_dir, "cannot move the simulated sequence into place") from None


def prepare_out_dir(out_dir: Path, overwrite: bool) -> None:
    """Create ``out_dir``; refuse a non-empty one unless ``overwrite`` (:func:`check_out_dir`)."""
    check_out_dir(out_dir, overwrite)
    (out_dir / "velodyne").mkdir(parents=True, exist_ok=True)
    (out_dir / "labels").mkdir(parents=True, exist_ok=True)
    (out_dir / "object_ids").mkdir(parents=True, exist_ok=True)


def remove_stale(out_dir: Path, frames: int) -> None:
    """Delete scans and labels numbered ``frames`` or above left by an older run."""
    for sub, ext in (("velodyne", ".bin"), ("labels", ".label"), ("object_ids", ".npy")):
        for path in (out_dir / sub).glob(f"*{ext}"):
            stem = path.stem
            if stem.isdigit() and int(stem) >= frames:
                path.unlink()


def write_scan(out_dir: Path, index: int, points: np.ndarray, intensity: np.ndarray,
               label: np.ndarray, objects: np.ndarray | None = None) -> None:
    """One scan's ``.bin`` and ``.label`` files (and ``object_ids/*.npy`` when given)."""
    data = np.empty((len(points), 4), dtype="<f4")
    data[:, :3] = points
    data[:, 3] = intensity
    atomic_write(out_dir / "velodyne" / f"{index:06d}.bin", data.tobytes())
    atomic_write(out_dir / "labels" / f"{index:06d}.label", label.astype("<u4").tobytes())
    if objects is not None:
        buf = io.BytesIO()
        np.save(buf, np.asarray(objects, dtype="<u4"), allow_pickle=False)
        (out_dir / "object_ids").mkdir(exist_ok=True)
        atomic_write(out_dir / "object_ids" / f"{index:06d}.npy", buf.getvalue())


def write_metadata(out_dir: Path, lidar_poses: np.ndarray, tr: np.ndarray,
                   manifest: dict, origin: np.ndarray | None = None) -> None:
    """poses.txt (camera frame, re-based to identity), times.txt, calib.txt, manifest.json.

    ``origin`` (4x4 LiDAR pose) is the pose written as identity; default the
    first of ``lidar_poses``. Later sessions of a multi-session world pass the
    first session's first pose, so every session's poses share one frame.
    """
    origin = lidar_poses[0] if origin is None else origin
    rel = np.linalg.inv(origin) @ lidar_poses
    cam = tr @ rel @ np.linalg.inv(tr)
    atomic_write(out_dir / "poses.txt", poses_text(cam).encode())
    atomic_write(out_dir / "times.txt", times_text(len(lidar_poses)).encode())
    atomic_write(out_dir / "calib.txt", calib_text(tr).encode())
    atomic_write(out_dir / "manifest.json",
                 (json.dumps(manifest, indent=2, sort_keys=True) + "\n").encode())
