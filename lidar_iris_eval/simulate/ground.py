"""The ground: a smooth height field with raised curbs off the road.

Two rasters over the world's extent describe it:

- ``height``: road-surface height, sampled on a coarse grid and interpolated
  bilinearly (gentle slopes and undulations need no finer grid);
- ``region``: road / sidewalk / terrain per fine cell. Sidewalk and terrain sit
  ``curb`` metres above the road, so a kerb face appears wherever the region
  changes from road to anything else.

A ray is cast by Newton's method against the road surface and against the
raised surface; which of the two (or the kerb face between them) it hits
depends on the region under each candidate point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.simulate import labels

REGION_ROAD, REGION_SIDEWALK, REGION_TERRAIN = 0, 1, 2
REGION_LABEL = np.array([labels.ROAD, labels.SIDEWALK, labels.TERRAIN], dtype=np.uint16)


@dataclass(frozen=True)
class Ground:
    """Height field plus region raster (see module docstring)."""

    origin: tuple[float, float]  # world (x, y) of cell (0, 0) corner
    height_cell: float
    height: np.ndarray  # (ny, nx) float64, sampled at cell corners
    region_cell: float
    region: np.ndarray  # (my, mx) uint8
    curb: float = 0.12
    #: Newton steps of the ray-ground intersection after the tangent-plane guess; 2 is
    #: enough for the gentle urban grades (and keeps those worlds byte-identical), the
    #: rougher natural terrain (:mod:`~lidar_iris_eval.simulate.nature`) takes more
    newton_steps: int = 2

    def elevation(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, ...]:
        """Road-surface height and its gradient ``(z, dz/dx, dz/dy)`` at (x, y)."""
        h = self.height
        u = (x - self.origin[0]) / self.height_cell
        v = (y - self.origin[1]) / self.height_cell
        i = np.minimum(np.maximum(u.astype(np.int64), 0), h.shape[1] - 2)
        j = np.minimum(np.maximum(v.astype(np.int64), 0), h.shape[0] - 2)
        fu = u - i
        fv = v - j
        z00, z10 = h[j, i], h[j, i + 1]
        z01, z11 = h[j + 1, i], h[j + 1, i + 1]
        a = z10 - z00
        b = z01 - z00
        c = z11 - z10 - z01 + z00
        z = z00 + a * fu + b * fv + c * fu * fv
        gx = (a + c * fv) / self.height_cell
        gy = (b + c * fu) / self.height_cell
        return z, gx, gy

    def region_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Region code (road 0, sidewalk 1, terrain 2) of the cell under (x, y)."""
        i = np.floor((x - self.origin[0]) / self.region_cell).astype(np.int64)
        j = np.floor((y - self.origin[1]) / self.region_cell).astype(np.int64)
        i = np.clip(i, 0, self.region.shape[1] - 1)
        j = np.clip(j, 0, self.region.shape[0] - 1)
        return self.region[j, i]

    def surface_height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Height of the visible ground surface (road, or road + curb elsewhere)."""
        z = self.elevation(x, y)[0]
        return z + self.curb * (self.region_at(x, y) != REGION_ROAD)


def cast_ground(
    ground: Ground, origin: np.ndarray, dirs: np.ndarray, max_range: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance, region code and unit normal of the ground hit of each ray.

    Rays that do not reach the ground within ``max_range`` get ``inf``.
    Kerb faces get the sidewalk region and a horizontal normal.

    The road surface is found by two Newton steps from the tangent plane under
    the sensor (the surface is smooth, so the error after them is far below a
    millimetre); the raised surface ``curb`` higher then follows from one more
    step, since it is parallel to the road surface.
    """
    n = len(dirs)
    t_out = np.full(n, np.inf)
    reg_out = np.zeros(n, dtype=np.uint8)
    nrm_out = np.zeros((n, 3))
    nrm_out[:, 2] = 1.0
    z0, gx0, gy0 = ground.elevation(np.array([origin[0]]), np.array([origin[1]]))
    denom = gx0[0] * dirs[:, 0] + gy0[0] * dirs[:, 1] - dirs[:, 2]
    with np.errstate(divide="ignore"):
        t = (origin[2] - z0[0]) / denom  # tangent-plane guess
    cand = np.nonzero((denom > 1e-4) & (t < max_range * 1.5))[0]
    if len(cand) == 0:
        return t_out, reg_out, nrm_out
    d = dirs[cand]
    t = t[cand]
    steps = ground.newton_steps
    for it in range(steps + 1):
        p = origin + t[:, None] * d
        z, gx, gy = ground.elevation(p[:, 0], p[:, 1])
        f = p[:, 2] - z
        df = d[:, 2] - gx * d[:, 0] - gy * d[:, 1]
        if it < steps:
            with np.errstate(divide="ignore", invalid="ignore"):
                t = t - f / df
    ok = (np.abs(f) < 1e-4) & (t > 0) & (df < 0) & (t <= max_range + 1.0)
    cand, d, t_lo, df, gx, gy = cand[ok], d[ok], t[ok], df[ok], gx[ok], gy[ok]
    t_hi = t_lo + ground.curb / df
    p_hi = origin + t_hi[:, None] * d
    p_lo = origin + t_lo[:, None] * d
    r_hi = ground.region_at(p_hi[:, 0], p_hi[:, 1])
    r_lo = ground.region_at(p_lo[:, 0], p_lo[:, 1])
    on_raised = (r_hi != REGION_ROAD) & (t_hi > 0)
    kerb = ~on_raised & (r_lo != REGION_ROAD)
    t = np.where(on_raised, t_hi, t_lo)
    region = np.where(on_raised, r_hi, r_lo)
    normal = np.stack([-gx, -gy, np.ones_like(gx)], 1)
    if kerb.any():
        # bisection for the road -> raised transition between t_hi and t_lo
        a, b = np.maximum(t_hi[kerb], 0.0), t_lo[kerb]
        dk = d[kerb]
        for _ in range(7):
            mid = 0.5 * (a + b)
            pm = origin + mid[:, None] * dk
            raised = ground.region_at(pm[:, 0], pm[:, 1]) != REGION_ROAD
            b = np.where(raised, mid, b)
            a = np.where(raised, a, mid)
        t[kerb] = b
        region[kerb] = REGION_SIDEWALK
        hz = -dk
        hz[:, 2] = 0.0
        normal[kerb] = hz
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    keep = t <= max_range
    t_out[cand[keep]] = t[keep]
    reg_out[cand[keep]] = region[keep]
    nrm_out[cand[keep]] = normal[keep]
    return t_out, reg_out, nrm_out
