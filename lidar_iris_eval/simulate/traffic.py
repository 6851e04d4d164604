"""Moving cars: traffic that differs between passes over the same place.

Cars move along the ego car's own driven line (so they are always on a road
the sensor sees): some drive ahead or behind in the ego lane at a slowly
varying gap, others come the opposite way in the other lane at their own
speed. Their positions depend on time only, so a revisit meets different
traffic while the static world stays identical.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lidar_iris_eval.simulate import labels
from lidar_iris_eval.simulate.ground import Ground
from lidar_iris_eval.simulate.raycast import Primitives, empty_primitives, make_primitives
from lidar_iris_eval.simulate.world import car_rows


@dataclass(frozen=True)
class Traffic:
    """Moving cars described relative to the ego line (arc-length ``s``)."""

    line: np.ndarray  # (n,2) ego positions per frame
    line_s: np.ndarray  # (n,) arc length per frame
    oncoming: np.ndarray  # (k,) bool
    gap: np.ndarray  # (k,) metres ahead (+) / behind (-) for followers
    s0: np.ndarray  # (k,) start arc length for oncoming cars
    speed: np.ndarray  # (k,) metres per frame for oncoming cars
    lateral: np.ndarray  # (k,) metres left of the ego line
    seeds: np.ndarray  # (k,) per-car shape seed
    first_instance: int

    def primitives(self, frame: int, ground: Ground) -> Primitives:
        """The moving cars' primitives at ``frame``."""
        if len(self.gap) == 0:
            return empty_primitives()
        s_end = self.line_s[-1]
        s_ego = self.line_s[frame]
        wobble = 3.0 * np.sin(0.02 * frame + self.seeds % 7)
        s = np.where(self.oncoming, (self.s0 - self.speed * frame) % s_end,
                     s_ego + self.gap + wobble)
        ok = (s >= 0) & (s <= s_end)
        rows: list[tuple] = []
        for k in np.nonzero(ok)[0]:
            x = np.interp(s[k], self.line_s, self.line[:, 0])
            y = np.interp(s[k], self.line_s, self.line[:, 1])
            ds = 1.0
            x2 = np.interp(min(s[k] + ds, s_end), self.line_s, self.line[:, 0])
            y2 = np.interp(min(s[k] + ds, s_end), self.line_s, self.line[:, 1])
            heading = np.arctan2(y2 - y, x2 - x)
            left = np.array([-np.sin(heading), np.cos(heading)])
            x, y = np.array([x, y]) + self.lateral[k] * left
            if np.hypot(x - self.line[frame, 0], y - self.line[frame, 1]) < 3.0:
                continue  # never drive through the ego car
            z = float(ground.elevation(np.array([x]), np.array([y]))[0][0])
            yaw = heading + (np.pi if self.oncoming[k] else 0.0)
            rng = np.random.default_rng(int(self.seeds[k]))
            rows.extend(car_rows(rng, x, y, z, yaw, labels.MOVING_CAR,
                                 self.first_instance + int(k)))
        return make_primitives(rows)


def make_traffic(
    rng: np.random.Generator, line: np.ndarray, count: int, first_instance: int
) -> Traffic:
    """``count`` moving cars along the ego positions ``line`` ((frames, 2))."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(line, axis=0), axis=1))])
    # make arc length strictly increasing for interpolation (stops repeat a position)
    s = s + 1e-6 * np.arange(len(s))
    oncoming = rng.random(count) < 0.6
    gap = rng.choice([-1.0, 1.0], count) * rng.uniform(9.0, 40.0, count)
    return Traffic(
        line=line,
        line_s=s,
        oncoming=oncoming,
        gap=gap,
        s0=rng.uniform(0.0, s[-1], count),
        speed=rng.uniform(0.6, 1.4, count),
        lateral=np.where(oncoming, rng.uniform(3.0, 3.6, count), 0.0),
        seeds=rng.integers(0, 2**31, count),
        first_instance=first_instance,
    )
