"""The likelihood-field range sensor model (Thrun, Burgard, Fox: Probabilistic Robotics, 6.4).

Each beam's end point is projected into the map for every particle; its probability is a
mixture of a hit (a Gaussian in the distance from the end point to the nearest obstacle) and a
uniform random reading::

    p(z_k | x, m) = z_hit * exp(-d^2 / (2 sigma_hit^2)) + z_rand / z_max

(amcl's form: the Gaussian is not normalized, so ``z_hit`` and ``z_rand`` are relative
weights). Readings at or beyond the maximum range carry no end point and are skipped, as are
NaN, below-minimum and non-finite ranges. Beams are subsampled evenly to ``max_beams`` like
amcl's ``max_beams``. The per-cell log-probability is precomputed from the distance field, so a
particle's log-likelihood is a sum of table lookups; an end point off the map counts as at the
maximum distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from planar_map import GridMap, distance_field

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class SensorModelConfig:
    """Likelihood-field parameters (amcl's names).

    Attributes:
        z_hit: weight of the hit component.
        z_rand: weight of the random component.
        sigma_hit: standard deviation of the hit Gaussian (m).
        max_distance: distance field truncation (laser_likelihood_max_dist, m).
        max_beams: beams used per scan, evenly spaced.
        laser_x: the lidar's x in base_link (m).
        laser_y: its y (m).
        laser_yaw: its yaw in base_link (rad).
        min_range: ranges below this are ignored (m; <= 0: the scan's range_min).
        max_range: ranges at or above this are max-range readings (m; <= 0: the scan's).
    """

    z_hit: float = 0.5
    z_rand: float = 0.5
    sigma_hit: float = 0.2
    max_distance: float = 2.0
    max_beams: int = 60
    laser_x: float = -0.064
    laser_y: float = 0.0
    laser_yaw: float = 0.0
    min_range: float = -1.0
    max_range: float = -1.0


@dataclass(frozen=True)
class Beams:
    """The usable beams of one scan, in ``base_link``.

    Attributes:
        x: end point x of each beam, in base_link (m).
        y: end point y (m).
        range_max: the range that counts as "no return" (for the random component, m).
    """

    x: FloatArray
    y: FloatArray
    range_max: float

    @property
    def count(self) -> int:
        """Number of beams."""
        return int(self.x.size)


def select_beams(ranges: npt.ArrayLike, angle_min: float, angle_increment: float,
                 range_min: float, range_max: float, config: SensorModelConfig) -> Beams:
    """Subsample a LaserScan to ``max_beams`` and keep the beams with a usable return.

    Raises:
        ValueError: the scan's geometry is unusable (no ranges, a zero or non-finite angle
            increment, non-finite limits).
    """
    r = np.asarray(ranges, dtype=np.float64).ravel()
    if r.size == 0:
        raise ValueError('no ranges')
    if not (math.isfinite(angle_min) and math.isfinite(angle_increment) and angle_increment != 0):
        raise ValueError(f'bad angles (angle_min {angle_min}, increment {angle_increment})')
    lo = config.min_range if config.min_range > 0 else range_min
    hi = config.max_range if config.max_range > 0 else range_max
    if not (math.isfinite(lo) and math.isfinite(hi) and hi > 0):
        raise ValueError(f'bad range limits ({range_min}, {range_max})')
    n = r.size
    count = max(2, min(config.max_beams, n))
    index = np.unique(np.round(np.linspace(0, n - 1, count)).astype(np.int64))
    picked = r[index]
    with np.errstate(invalid='ignore'):
        usable = np.isfinite(picked) & (picked >= max(lo, 0.0)) & (picked < hi)
    index, picked = index[usable], picked[usable]
    angle = config.laser_yaw + angle_min + index * angle_increment
    x = config.laser_x + picked * np.cos(angle)
    y = config.laser_y + picked * np.sin(angle)
    return Beams(x, y, float(hi))


class LikelihoodField:
    """The per-cell log-probability table of one map, and the particle scoring on it.

    Derived from the map and the model parameters only: a cache, rebuilt when the map changes.
    """

    def __init__(self, grid: GridMap, config: SensorModelConfig) -> None:
        self.grid = grid
        self.config = config
        self.distance = distance_field(grid.occupied(), grid.resolution, config.max_distance)
        # log p per cell (flattened) and for an end point off the map, per z_max: the random
        # component is uniform over [0, z_max), and z_max is the scan's unless configured.
        self._tables: dict[float, tuple[FloatArray, float]] = {}

    def _table(self, z_max: float) -> tuple[FloatArray, float]:
        table = self._tables.get(z_max)
        if table is None:
            c = self.config
            floor = c.z_rand / z_max
            d = self.distance.astype(np.float64).ravel()
            per_cell = np.log(c.z_hit * np.exp(-(d * d) / (2.0 * c.sigma_hit ** 2)) + floor)
            off = math.log(c.z_hit * math.exp(-(c.max_distance ** 2) / (2.0 * c.sigma_hit ** 2))
                           + floor)
            table = (np.asarray(per_cell, dtype=np.float64), off)
            self._tables[z_max] = table
        return table

    def log_likelihood(self, particles: FloatArray, beams: Beams) -> FloatArray:
        """Sum over beams of log p(z_k | x, m), for each particle row ``(x, y, yaw)``."""
        if beams.count == 0:
            return np.zeros(particles.shape[0])
        g = self.grid
        c = np.cos(particles[:, 2])[:, None]
        s = np.sin(particles[:, 2])[:, None]
        ex = particles[:, 0:1] + c * beams.x - s * beams.y
        ey = particles[:, 1:2] + s * beams.x + c * beams.y
        col = np.floor((ex - g.origin_x) / g.resolution).astype(np.int64)
        row = np.floor((ey - g.origin_y) / g.resolution).astype(np.int64)
        inside = (col >= 0) & (col < g.width) & (row >= 0) & (row < g.height)
        flat = np.where(inside, row * g.width + col, 0)
        per_cell, off_map = self._table(beams.range_max)
        logp = np.where(inside, per_cell[flat], off_map)
        return np.asarray(logp.sum(axis=1), dtype=np.float64)
