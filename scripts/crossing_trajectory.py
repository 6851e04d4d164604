#!/usr/bin/env python
"""A drive that comes back across its own start at a chosen angle (a KITTI pose file).

    python scripts/crossing_trajectory.py OUT.txt --angle 90 [--step 1.2]
    liris simulate SEQ --trajectory OUT.txt --sensor os1-64 --azimuth-steps 1024 --seed 11

Most simulated worlds revisit a street in the same or the reverse direction.
A real drive also comes back across a place at an angle (an intersection
crossed the other way), which is where segment methods have failed on real
scans: the two visits see the objects from other sides. The path leaves the
origin along +x, drives a ``side`` m square block anticlockwise, then comes
back through the origin heading ``--angle`` degrees from its first heading and
goes on ``tail`` m; corners are rounded (Chaikin's corner cutting, 4 rounds)
and poses are placed every ``--step`` m. The file holds camera-frame KITTI
poses for ``liris simulate --trajectory`` with its default calibration (the
LiDAR poses ``inv(Tr) P Tr`` are the drive above). docs/esm.md ("Weights
trained on real segments, and how a set grows") uses it at 90 and 70 degrees.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from lidar_iris_eval.atomic import atomic_write
from lidar_iris_eval.cli import run_guarded
from lidar_iris_eval.errors import LirisError


def crossing_path(angle_deg: float, step: float, side: float = 70.0,
                  tail: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """``(xy (n, 2), yaw (n,))`` of the drive (module docstring), in metres and radians."""
    heading = np.array([np.cos(np.radians(angle_deg)), np.sin(np.radians(angle_deg))])
    poly = np.array([[0.0, 0.0], [side, 0.0], [side, side], -heading * side, [0.0, 0.0],
                     heading * tail])
    for _ in range(4):  # Chaikin: each edge replaced by its 1/4 and 3/4 points
        cut = [poly[0]]
        for a, b in zip(poly[:-1], poly[1:], strict=True):
            cut += [0.75 * a + 0.25 * b, 0.25 * a + 0.75 * b]
        cut.append(poly[-1])
        poly = np.asarray(cut)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s = np.arange(0.0, arc[-1], step)
    xy = np.column_stack([np.interp(s, arc, poly[:, 0]), np.interp(s, arc, poly[:, 1])])
    d = np.gradient(xy, axis=0)
    return xy, np.arctan2(d[:, 1], d[:, 0])


def camera_poses(xy: np.ndarray, yaw: np.ndarray, tr: np.ndarray) -> np.ndarray:
    """KITTI rows (n, 12) of the camera poses ``Tr L inv(Tr)`` of planar LiDAR poses ``L``."""
    rows = []
    for (x, y), t in zip(xy, yaw, strict=True):
        lidar = np.eye(4)
        lidar[:2, :2] = [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]]
        lidar[:2, 3] = (x, y)
        rows.append((tr @ lidar @ np.linalg.inv(tr))[:3].ravel())
    return np.asarray(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path, help="the KITTI pose file to write (camera frame)")
    ap.add_argument("--angle", type=float, default=90.0,
                    help="heading of the return through the start, from the first (deg)")
    ap.add_argument("--step", type=float, default=1.2, help="metres between poses")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing OUT")
    args = ap.parse_args(argv)

    def body() -> None:
        from lidar_iris_eval.simulate.writer import default_tr

        if not args.step > 0:
            raise LirisError("--step", f"must be positive, got {args.step}")
        if not 10 <= abs(args.angle) <= 170:
            raise LirisError("--angle", "must be between 10 and 170 degrees (a crossing)")
        if args.out.exists() and not args.overwrite:
            raise LirisError(args.out, "exists; give --overwrite to replace it")
        xy, yaw = crossing_path(args.angle, args.step)
        rows = camera_poses(xy, yaw, default_tr())
        text = "".join(" ".join(f"{v:.9e}" for v in r) + "\n" for r in rows)
        atomic_write(args.out, text, what="trajectory")
        print(f"{len(rows)} poses, {float(np.sum(np.linalg.norm(np.diff(xy, axis=0), axis=1))):.0f}"
              f" m, to {args.out}")

    run_guarded(body)


if __name__ == "__main__":
    main(sys.argv[1:])
