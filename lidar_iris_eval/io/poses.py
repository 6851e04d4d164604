"""Pose and calibration files: KITTI 3×4 poses, TUM trajectories, KITTI calib.

KITTI ground-truth poses are those of the left camera (x right, y down,
z forward). ``calib.txt`` holds ``Tr``, which maps Velodyne points into the
camera frame, so a LiDAR-frame pose is ``inv(Tr) · T_cam · Tr``.

Rule ``orthonormal-rotation``: the 3×3 rotation of every pose and of ``Tr``
must satisfy ``max |RᵀR − I| <= ROTATION_TOLERANCE`` and ``det R > 0``. A
zeroed, scaled or mirrored rotation is reported naming its file and line
instead of silently changing the LiDAR-frame ground truth (``inv(Tr)`` of a
singular ``Tr`` does not exist at all).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lidar_iris_eval.errors import LirisError, read_text

#: rule ``orthonormal-rotation``: KITTI's poses are orthonormal to 2e-7 and poses printed
#: with 6 decimals to about 1e-6; 1e-3 still rejects any zeroed, scaled or sheared matrix
ROTATION_TOLERANCE = 1e-3


def rotation_problem(rotation: np.ndarray) -> str | None:
    """Why the 3×3 ``rotation`` breaks rule ``orthonormal-rotation``, or None."""
    error = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if not error <= ROTATION_TOLERANCE:
        return (f"rotation is not orthonormal (max |R^T R - I| = {error:.3g} > "
                f"{ROTATION_TOLERANCE:g}; rule orthonormal-rotation)")
    if np.linalg.det(rotation) <= 0:
        return "rotation is a reflection (det R < 0; rule orthonormal-rotation)"
    return None


def check_rotations(poses: np.ndarray, path: Path, line_numbers: list[int] | None,
                    what: str) -> None:
    """Raise a LirisError naming the first pose (file:line) whose rotation is not one."""
    rotations = np.asarray(poses)[:, :3, :3]
    errors = np.abs(np.einsum("nji,njk->nik", rotations, rotations) - np.eye(3)).max(axis=(1, 2))
    bad = ~(errors <= ROTATION_TOLERANCE) | (np.linalg.det(rotations) <= 0)
    if bad.any():
        first = int(np.argmax(bad))
        where = f"{path}:{line_numbers[first]}" if line_numbers else f"{path} (pose {first})"
        raise LirisError(where, f"{what}: {rotation_problem(rotations[first])}")


def is_number(text: str) -> bool:
    """Whether ``text`` reads as a float (a header line of a pose or loop table is not)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def check_finite(values, where: str, what: str) -> None:
    """Raise one LirisError at ``where`` (``file:line``) if a value of a pose row is NaN or inf.

    Every pose reader (KITTI, TUM, the dataset tables, Oxford's INS) calls it
    per row, so a non-finite pose never reaches the SVDs and interpolations.
    """
    if not np.all(np.isfinite(np.asarray(values, dtype=np.float64))):
        raise LirisError(where, f"malformed {what} line (NaN or inf)")


def _read_rows(path: Path, expected: int, what: str) -> np.ndarray:
    """Parse a whitespace table whose rows each hold ``expected`` numbers."""
    return _read_numbered_rows(path, expected, what)[0]


def _read_numbered_rows(path: Path, expected: int, what: str) -> tuple[np.ndarray, list[int]]:
    """:func:`_read_rows` plus the 1-based line number of each row."""
    if not path.is_file():
        raise LirisError(path, f"{what} file not found")
    rows = []
    numbers = []
    for number, line in enumerate(read_text(path, f"{what} file").splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        parts = text.replace(",", " ").split()
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise LirisError(f"{path}:{number}", f"malformed {what} line (not numbers)") from None
        if len(values) != expected:
            raise LirisError(
                f"{path}:{number}",
                f"malformed {what} line: {len(values)} numbers, expected {expected}",
            )
        check_finite(values, f"{path}:{number}", what)
        rows.append(values)
        numbers.append(number)
    if not rows:
        raise LirisError(path, f"{what} file is empty")
    return np.asarray(rows, dtype=np.float64), numbers


def to_homogeneous(rows: np.ndarray) -> np.ndarray:
    """Rows of 12 numbers (row-major 3×4) to ``(N, 4, 4)`` matrices."""
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :4] = rows.reshape(-1, 3, 4)
    return poses


def read_kitti_poses(path: str | Path) -> np.ndarray:
    """Read a KITTI pose file: one row-major 3×4 matrix per line, ``(N, 4, 4)``."""
    path = Path(path)
    rows, numbers = _read_numbered_rows(path, 12, "KITTI pose")
    poses = to_homogeneous(rows)
    check_rotations(poses, path, numbers, "KITTI pose")
    return poses


def quaternion_to_matrix(q_xyzw: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(N, 4)`` in (x, y, z, w) order to ``(N, 3, 3)`` rotations."""
    q = q_xyzw / np.linalg.norm(q_xyzw, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=1),
        ],
        axis=1,
    )


def read_tum_poses(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory ``t x y z qx qy qz qw``: ``(times (N,), poses (N, 4, 4))``."""
    path = Path(path)
    rows, numbers = _read_numbered_rows(path, 8, "TUM pose")
    steps = np.diff(rows[:, 0])
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0)) + 1
        kind = "repeats" if steps[k - 1] == 0 else "is earlier than"
        raise LirisError(f"{path}:{numbers[k]}",
                         f"TUM pose stamps must increase: {rows[k, 0]:.9g} {kind} the stamp "
                         f"{rows[k - 1, 0]:.9g} of line {numbers[k - 1]}")
    quats = rows[:, 4:8]
    norms = np.linalg.norm(quats, axis=1)
    if np.any(norms < 1e-9):
        bad = int(np.argmax(norms < 1e-9))
        raise LirisError(path, f"malformed TUM pose line: zero quaternion in row {bad + 1}")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = quaternion_to_matrix(quats)
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], poses


def read_pose_file(path: str | Path, fmt: str = "auto") -> tuple[np.ndarray | None, np.ndarray]:
    """Read KITTI or TUM poses; ``fmt='auto'`` decides from the first data line's width.

    Returns ``(times or None, poses (N, 4, 4))``.
    """
    path = Path(path)
    if fmt == "auto":
        fmt = _guess_pose_format(path)
    if fmt == "kitti":
        return None, read_kitti_poses(path)
    if fmt == "tum":
        return read_tum_poses(path)
    raise LirisError(f"--pose-format {fmt}", "unknown pose format; choose kitti, tum or auto")


def _guess_pose_format(path: Path) -> str:
    if not path.is_file():
        raise LirisError(path, "pose file not found")
    for line in read_text(path, "pose file").splitlines():
        text = line.strip()
        if text and not text.startswith("#"):
            width = len(text.replace(",", " ").split())
            if width == 12:
                return "kitti"
            if width == 8:
                return "tum"
            raise LirisError(
                path, f"malformed pose line: {width} numbers (12 for KITTI 3×4, 8 for TUM)"
            )
    raise LirisError(path, "pose file is empty")


def read_calib(path: str | Path) -> np.ndarray:
    """Read ``Tr`` (Velodyne → camera) from a KITTI ``calib.txt`` as a 4×4 matrix.

    Accepts ``Tr:`` (odometry) or ``Tr_velo_to_cam:`` (raw) lines; other lines
    (P0..P3) are ignored.
    """
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "calibration file not found")
    for number, line in enumerate(read_text(path, "calibration file").splitlines(), start=1):
        key, _, rest = line.partition(":")
        if key.strip() in ("Tr", "Tr_velo_to_cam"):
            try:
                values = np.array([float(v) for v in rest.split()])
            except ValueError:
                raise LirisError(f"{path}:{number}", "malformed Tr line (not numbers)") from None
            if values.size != 12 or not np.all(np.isfinite(values)):
                raise LirisError(
                    f"{path}:{number}", f"malformed Tr line: {values.size} numbers, expected 12"
                )
            tr = to_homogeneous(values[None])[0]
            problem = rotation_problem(tr[:3, :3])
            if problem is not None:
                raise LirisError(f"{path}:{number}", f"Tr (Velodyne to camera): {problem}")
            return tr
    raise LirisError(path, "no 'Tr:' line (Velodyne to camera transform)")


def camera_to_lidar(camera_poses: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """Convert camera-frame poses to LiDAR-frame poses: ``inv(Tr) · T · Tr``."""
    return np.linalg.inv(tr) @ camera_poses @ tr


def write_kitti_poses(path: str | Path, poses: np.ndarray) -> None:
    """Write ``(N, 4, 4)`` poses as KITTI 3×4 rows (the caller makes it atomic)."""
    rows = np.asarray(poses)[:, :3, :4].reshape(len(poses), 12)
    np.savetxt(path, rows, fmt="%.9e")
