"""Street grids, routes with known revisits, and the sensor poses along them.

A route is a list of corner nodes of a street grid, driven in order. The
templates below put the loops where the ground truth needs them:

- ``same``: laps of one rectangle counter-clockwise, so every later lap
  revisits the first in the same direction;
- ``reverse``: one lap counter-clockwise, a U-turn, then laps clockwise: the
  revisits are driven the opposite way (as in KITTI 08);
- ``mixed``: one lap, part of a second lap in the same direction, a U-turn,
  then clockwise: both kinds of revisit.

The car keeps right with a lane offset redrawn for every block (0 to
``lateral_max`` metres right of the centre line), so two passes differ by up to
``2 * lateral_max`` laterally when driven in opposite directions. Speed varies
slowly and drops in turns; heading gets a slow random error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from lidar_iris_eval.errors import LirisError
from lidar_iris_eval.simulate.ground import Ground

ROUTES = ("same", "reverse", "mixed")


@dataclass(frozen=True)
class RouteParams:
    """How the ego car drives a route."""

    lateral_max: float = 1.5
    step: float = 1.0  # metres per frame at cruising speed (10 m/s at 10 Hz)
    speed_jitter: float = 0.12
    heading_noise_deg: float = 1.5
    tilt_noise_deg: float = 0.3
    uturn_radius: float = 4.5
    smoothing: float = 4.0  # metres, Gaussian sigma that rounds corners
    lateral_accel: float = 6.0  # m/s^2, slows the car in turns


def street_grid(rng: np.random.Generator, nx: int, ny: int, block: tuple[float, float]):
    """Irregular grid lines: ``nx`` + 1 x positions and ``ny`` + 1 y positions."""
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(*block, nx))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(*block, ny))])
    return xs, ys


def route_corners(route: str, a: int, b: int, laps: int = 12) -> list[tuple[int, int]]:
    """Corner nodes (grid indices, rectangle ``a`` x ``b`` blocks) of a route template."""
    ccw = [(0, 0), (a, 0), (a, b), (0, b)]
    if route == "same":
        return ccw * laps + [(0, 0)]
    if route == "reverse":
        cw = [(0, 0), (0, b), (a, b), (a, 0)]
        return ccw + cw * laps + [(0, 0)]
    if route == "mixed":
        cw_from_ab = [(a, 0), (0, 0), (0, b), (a, b)]
        return ccw + [(0, 0), (a, 0), (a, b)] + cw_from_ab * laps
    raise LirisError("--route", f"unknown route {route!r}; choose from {', '.join(ROUTES)}")


def grid_waypoints(
    corners: list[tuple[int, int]], xs: np.ndarray, ys: np.ndarray, rng: np.random.Generator,
    params: RouteParams, length: float,
) -> np.ndarray:
    """Dense (0.5 m) waypoints of the driven line, kept right, until ``length`` metres.

    The lane offset is redrawn for every leg between corners and eased in over
    the first 20 m of the leg, like a gentle lane change.
    """
    pts = [np.array([xs[i], ys[j]]) for i, j in corners]
    out: list[np.ndarray] = []
    total = 0.0
    prev_off = rng.uniform(0.0, params.lateral_max)
    for k in range(len(pts) - 1):
        a, b = pts[k], pts[k + 1]
        u = (b - a) / np.linalg.norm(b - a)
        right = np.array([u[1], -u[0]])
        off = rng.uniform(0.0, params.lateral_max)
        seg_len = float(np.linalg.norm(b - a))
        s = np.arange(0.0, seg_len, 0.5)
        ease = np.clip(s / 20.0, 0.0, 1.0)
        ease = ease * ease * (3 - 2 * ease)
        o = prev_off + (off - prev_off) * ease
        out.append(a + s[:, None] * u + o[:, None] * right)
        prev_off = off
        total += seg_len
        if k + 2 < len(pts) and np.allclose(pts[k + 2], a):  # U-turn at b
            th = np.linspace(0.0, np.pi, 24)
            r = params.uturn_radius
            out.append(b + r * (np.cos(th)[:, None] * right + np.sin(th)[:, None] * u))
            total += np.pi * r
        if total > length + 50:
            break
    return np.concatenate(out)


def _smooth_noise(rng: np.random.Generator, n: int, sigma: float) -> np.ndarray:
    """Unit-variance Gaussian noise low-pass filtered over ``sigma`` samples."""
    x = ndimage.gaussian_filter1d(rng.normal(size=n + 8 * int(sigma)), sigma, mode="wrap")
    # the variance of filtered white noise is known: 1 / (2 sigma sqrt(pi))
    return x[:n] * np.sqrt(2.0 * sigma * np.sqrt(np.pi))


def drive(
    waypoints: np.ndarray, frames: int, rng: np.random.Generator, params: RouteParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions (frames, 2), headings (frames,) and arc lengths along a smoothed line.

    The line is smoothed to round its corners, then sampled one frame per
    0.1 s at a speed that varies slowly and drops where the curvature is high.
    """
    sig = params.smoothing / 0.5
    line = np.stack([ndimage.gaussian_filter1d(waypoints[:, k], sig, mode="nearest")
                     for k in range(2)], 1)
    d = np.diff(line, axis=0)
    seg = np.linalg.norm(d, axis=1)
    keep = np.concatenate([[True], seg > 1e-6])
    line = line[keep]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    heading = np.unwrap(np.arctan2(np.gradient(line[:, 1]), np.gradient(line[:, 0])))
    curv = np.abs(np.gradient(heading) / np.maximum(np.gradient(s), 1e-6))
    curv = ndimage.gaussian_filter1d(curv, 4)
    v_turn = np.sqrt(params.lateral_accel / np.maximum(curv, 1e-6)) / 10.0  # m per frame
    cap = np.interp(np.arange(0, s[-1], 0.5), s, np.minimum(v_turn, params.step))
    cap = np.maximum(cap, 0.5 * params.step)
    jitter = np.clip(1.0 + params.speed_jitter * _smooth_noise(rng, frames, 30.0), 0.5, 1.5)
    pos_s = np.zeros(frames)
    for i in range(1, frames):
        here = cap[min(int(pos_s[i - 1] / 0.5), len(cap) - 1)]
        pos_s[i] = pos_s[i - 1] + here * jitter[i]
    if pos_s[-1] > s[-1]:
        raise LirisError("--frames", f"route too short for {frames} frames")
    xy = np.stack([np.interp(pos_s, s, line[:, 0]), np.interp(pos_s, s, line[:, 1])], 1)
    yaw = np.interp(pos_s, s, heading)
    yaw = yaw + np.deg2rad(params.heading_noise_deg) * _smooth_noise(rng, frames, 15.0)
    return xy, yaw, pos_s


def poses_on_ground(
    ground: Ground, xy: np.ndarray, yaw: np.ndarray, mount_height: float,
    rng: np.random.Generator, tilt_noise_deg: float,
) -> np.ndarray:
    """Sensor-to-world 4x4 poses of a car on the road surface at ``xy`` facing ``yaw``.

    The car's up axis follows the local road normal (plus a small random
    roll/pitch), and the sensor sits ``mount_height`` above the road along it.
    """
    z, gx, gy = ground.elevation(xy[:, 0], xy[:, 1])
    up = np.stack([-gx, -gy, np.ones_like(gx)], 1)
    tilt = np.deg2rad(tilt_noise_deg) * rng.normal(size=(len(xy), 2))
    up[:, :2] += tilt
    up /= np.linalg.norm(up, axis=1, keepdims=True)
    fwd = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], 1)
    fwd -= (fwd * up).sum(1, keepdims=True) * up
    fwd /= np.linalg.norm(fwd, axis=1, keepdims=True)
    left = np.cross(up, fwd)
    poses = np.tile(np.eye(4), (len(xy), 1, 1))
    poses[:, :3, 0], poses[:, :3, 1], poses[:, :3, 2] = fwd, left, up
    poses[:, :3, 3] = np.stack([xy[:, 0], xy[:, 1], z], 1) + mount_height * up
    return poses


def read_kitti_poses(path) -> np.ndarray:
    """(N,4,4) poses from a KITTI pose file (12 numbers per line, row-major 3x4).

    The readers' own checks apply (:func:`lidar_iris_eval.io.poses.read_kitti_poses`):
    a NaN/inf row or a rotation that is not one (a scaled ``2 I``) is one error
    naming ``file:line``.
    """
    from lidar_iris_eval.io.poses import read_kitti_poses as read_checked

    poses = read_checked(path)
    if len(poses) < 2:
        raise LirisError(path, "expected at least 2 lines of 12 numbers (KITTI pose format)")
    return poses


def trajectory_from_file(
    poses_cam: np.ndarray, tr: np.ndarray, frames: int | None
) -> np.ndarray:
    """LiDAR-frame poses ``inv(Tr) T_cam Tr`` of a camera-frame KITTI trajectory."""
    if frames is not None:
        poses_cam = poses_cam[:frames]
    return np.linalg.inv(tr) @ poses_cam @ tr
