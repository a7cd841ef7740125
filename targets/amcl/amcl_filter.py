"""The particle filter: initialization, prediction, weighting, KLD-adaptive low-variance
resampling with augmented-MCL recovery, and the pose estimate of the best cluster.

Probabilistic Robotics (Thrun, Burgard, Fox 2005): Monte Carlo localization (8.3), low-variance
resampling (Table 4.4), augmented MCL (Table 8.3, ``alpha_slow``/``alpha_fast``, off by default
as in amcl). Fox 2003 ("Adapting the sample size in particle filters through KLD-sampling"):
the number of particles is the smallest n for which a histogram of the posterior over
0.5 m x 0.5 m x 10° bins is within ``pf_err`` (Kullback-Leibler) of the true one with
probability ``pf_z``. The count is found as Fox does, drawing from the weighted set and counting
the bins the draws fill; the new set itself is then drawn by low-variance resampling with that
count (one uniform number, the systematic comb), which keeps more diversity than independent
draws.

All randomness comes from ``self.rng`` (a ``numpy.random.Generator``): the same generator state
and the same inputs give the same particles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np
import numpy.typing as npt

from amcl_motion_model import MotionNoise, sample_motion_model_odometry
from planar_geometry import Pose

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass(frozen=True)
class FilterConfig:
    """Particle counts, KLD bound, histogram bins and recovery rates.

    Attributes:
        min_particles: never fewer particles than this.
        max_particles: never more (and the count at initialization).
        pf_err: KLD bound epsilon between the sampled and the true posterior.
        pf_z: probability that the bound holds (the normal quantile is taken of it).
        bin_xy: histogram bin side in x and y (m).
        bin_yaw: histogram bin side in yaw (rad).
        alpha_slow: augmented MCL, slow average rate of the mean likelihood (0: off).
        alpha_fast: augmented MCL, fast average rate (0: off).
    """

    min_particles: int = 500
    max_particles: int = 2000
    pf_err: float = 0.05
    pf_z: float = 0.99
    bin_xy: float = 0.5
    bin_yaw: float = math.radians(10.0)
    alpha_slow: float = 0.0
    alpha_fast: float = 0.0


def kld_sample_count(bins: IntArray | npt.ArrayLike, err: float, z: float) -> IntArray:
    """Fox 2003, eq. 13: particles needed when ``bins`` histogram bins hold mass (vectorized).

    n = (k - 1) / (2 err) * (1 - 2 / (9 (k - 1)) + sqrt(2 / (9 (k - 1))) z)^3; 0 for k <= 1.
    """
    k = np.asarray(bins, dtype=np.float64)
    k1 = np.maximum(k - 1.0, 1.0)
    b = 2.0 / (9.0 * k1)
    n = k1 / (2.0 * err) * (1.0 - b + np.sqrt(b) * z) ** 3
    out: IntArray = np.where(k <= 1.0, 0, np.ceil(n)).astype(np.int64)
    return out


class ParticleFilter:
    """Particles ``(x, y, yaw)`` in ``map`` with normalized weights.

    Attributes:
        particles: (N, 3) array.
        weights: (N,) array summing to 1.
        rng: the generator every random draw comes from.
        pose: the estimate ``[x, y, yaw]`` (mean of the heaviest cluster).
        covariance: its 3 x 3 covariance (x, y, yaw).
        log_w_slow: augmented MCL's slow average of the mean likelihood, as a log; -inf unset.
        log_w_fast: the fast one.
        updates_since_resample: sensor updates since the last resampling.
    """

    def __init__(self, config: FilterConfig, rng: np.random.Generator) -> None:
        self.config = config
        self.rng = rng
        self.particles: FloatArray = np.zeros((0, 3))
        self.weights: FloatArray = np.zeros(0)
        self.pose: FloatArray = np.zeros(3)
        self.covariance: FloatArray = np.zeros((3, 3))
        self.log_w_slow = -math.inf
        self.log_w_fast = -math.inf
        self.updates_since_resample = 0
        self._z = NormalDist().inv_cdf(config.pf_z)
        self._bin = np.array([config.bin_xy, config.bin_xy, config.bin_yaw])
        self._yaw_bins = max(1, round(2.0 * math.pi / config.bin_yaw))

    # -- initialization -------------------------------------------------------------------------

    def initialize_gaussian(self, mean: Pose, covariance: FloatArray) -> None:
        """``max_particles`` particles drawn around ``mean`` with a 3 x 3 ``covariance``."""
        cov = np.array(covariance, dtype=np.float64).reshape(3, 3)
        cov = 0.5 * (cov + cov.T)
        # A singular covariance (an exact pose) still gets a Cholesky factor.
        vals, vecs = np.linalg.eigh(cov)
        factor = vecs * np.sqrt(np.clip(vals, 0.0, None))
        n = self.config.max_particles
        draws = self.rng.standard_normal((n, 3)) @ factor.T
        particles = np.asarray(mean, dtype=np.float64) + draws
        particles[:, 2] = (particles[:, 2] + np.pi) % (2.0 * np.pi) - np.pi
        self._reset(particles)

    def initialize_uniform(self, free_cells: FloatArray, cell_size: float) -> None:
        """``max_particles`` particles spread uniformly over the free cells (global
        localization); ``free_cells`` holds the (x, y) centres."""
        self._reset(self._random_poses(self.config.max_particles, free_cells, cell_size))

    def _reset(self, particles: FloatArray) -> None:
        self.particles = particles
        self.weights = np.full(particles.shape[0], 1.0 / particles.shape[0])
        self.log_w_slow = -math.inf
        self.log_w_fast = -math.inf
        self.updates_since_resample = 0
        self.estimate()

    def _random_poses(self, n: int, free_cells: FloatArray, cell_size: float) -> FloatArray:
        pick = self.rng.integers(0, free_cells.shape[0], size=n)
        jitter = (self.rng.random((n, 2)) - 0.5) * cell_size
        out = np.empty((n, 3))
        out[:, :2] = free_cells[pick] + jitter
        out[:, 2] = self.rng.uniform(-np.pi, np.pi, size=n)
        return out

    # -- the filter steps ----------------------------------------------------------------------

    def predict(self, odom_before: Pose, odom_after: Pose, noise: MotionNoise) -> None:
        """Move the particles by the odometry's motion between two poses (odom frame)."""
        self.particles = sample_motion_model_odometry(self.particles, odom_before, odom_after,
                                                      noise, self.rng)

    def weigh(self, log_likelihood: FloatArray) -> bool:
        """Multiply the weights by the measurement likelihoods (given as logs).

        Returns:
            False (and nothing changed) when no likelihood is finite.
        """
        with np.errstate(divide='ignore'):
            log_w = np.log(self.weights) + log_likelihood
        top = float(np.max(log_w)) if log_w.size else -math.inf
        if not math.isfinite(top):
            return False
        w = np.exp(log_w - top)
        total = float(w.sum())
        self.weights = w / total
        # Mean likelihood over the set (weights were normalized): log of sum(w_prev * p) / N.
        log_w_avg = top + math.log(total) - math.log(self.weights.size)
        c = self.config
        if c.alpha_slow > 0.0 and c.alpha_fast > 0.0:
            self.log_w_slow = self._average(self.log_w_slow, log_w_avg, c.alpha_slow)
            self.log_w_fast = self._average(self.log_w_fast, log_w_avg, c.alpha_fast)
        self.updates_since_resample += 1
        return True

    @staticmethod
    def _average(log_w: float, log_new: float, alpha: float) -> float:
        # w += alpha (new - w), in logs; an unset average starts at the first value.
        if not math.isfinite(log_w):
            return log_new
        return float(np.logaddexp(math.log1p(-alpha) + log_w, math.log(alpha) + log_new))

    def recovery_probability(self) -> float:
        """Augmented MCL: the share of particles to draw at random, max(0, 1 - w_fast/w_slow)."""
        if not (math.isfinite(self.log_w_slow) and math.isfinite(self.log_w_fast)):
            return 0.0
        return max(0.0, 1.0 - math.exp(self.log_w_fast - self.log_w_slow))

    def resample(self, free_cells: FloatArray | None = None, cell_size: float = 0.05) -> None:
        """KLD-adaptive low-variance resampling; with augmented MCL on, some particles are
        replaced by random poses on ``free_cells``."""
        c = self.config
        cumulative = np.cumsum(self.weights)
        cumulative /= cumulative[-1]
        last = self.particles.shape[0] - 1
        # How many: Fox's bin counting over independent draws from the weighted set.
        draws = np.minimum(np.searchsorted(cumulative, self.rng.random(c.max_particles),
                                           side='right'), last)
        bins = self._bins(self.particles[draws])
        _, first = np.unique(bins, axis=0, return_index=True)
        fresh = np.zeros(c.max_particles, dtype=bool)
        fresh[first] = True
        filled = np.cumsum(fresh)
        n_drawn = np.arange(1, c.max_particles + 1)
        enough = (n_drawn >= kld_sample_count(filled, c.pf_err, self._z)) & (
            n_drawn >= c.min_particles)
        n = int(n_drawn[np.argmax(enough)]) if enough.any() else c.max_particles
        # Which: the low-variance comb over the cumulative weights.
        comb = (self.rng.random() + np.arange(n)) / n
        picked = np.minimum(np.searchsorted(cumulative, comb, side='right'), last)
        particles = self.particles[picked]
        w_diff = self.recovery_probability()
        if w_diff > 0.0 and free_cells is not None and free_cells.shape[0] > 0:
            inject = self.rng.random(n) < w_diff
            count = int(inject.sum())
            if count:
                particles[inject] = self._random_poses(count, free_cells, cell_size)
            # amcl resets the averages after injecting, so it does not inject for ever.
            self.log_w_slow = -math.inf
            self.log_w_fast = -math.inf
        self.particles = particles
        self.weights = np.full(n, 1.0 / n)
        self.updates_since_resample = 0

    # -- estimate ---------------------------------------------------------------------------------

    def _bins(self, particles: FloatArray) -> IntArray:
        b: IntArray = np.floor(particles / self._bin).astype(np.int64)
        b[:, 2] = np.floor((particles[:, 2] + np.pi) / self.config.bin_yaw).astype(np.int64)
        b[:, 2] %= self._yaw_bins
        return b

    def clusters(self) -> IntArray:
        """A cluster label per particle: particles in touching histogram bins (26-neighbours,
        yaw wrapping around) share a label, as amcl's kd-tree clustering."""
        bins = self._bins(self.particles)
        unique, inverse = np.unique(bins, axis=0, return_inverse=True)
        index = {tuple(int(v) for v in row): i for i, row in enumerate(unique)}
        parent = list(range(len(unique)))

        def find(i: int) -> int:
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        offsets = [(dx, dy, dt) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dt in (-1, 0, 1)
                   if (dx, dy, dt) > (0, 0, 0)]
        for (bx, by, bt), i in index.items():
            for dx, dy, dt in offsets:
                j = index.get((bx + dx, by + dy, (bt + dt) % self._yaw_bins))
                if j is not None:
                    ri, rj = find(i), find(j)
                    if ri != rj:
                        parent[rj] = ri
        roots = np.array([find(i) for i in range(len(unique))], dtype=np.int64)
        return np.asarray(roots[np.asarray(inverse).ravel()], dtype=np.int64)

    def estimate(self) -> None:
        """Set ``pose`` and ``covariance`` from the heaviest cluster of weighted particles."""
        if self.particles.shape[0] == 0:
            return
        labels = self.clusters()
        mass = np.bincount(labels, weights=self.weights)
        chosen = labels == int(np.argmax(mass))
        p = self.particles[chosen]
        w = self.weights[chosen]
        w = w / w.sum()
        yaw = math.atan2(float(w @ np.sin(p[:, 2])), float(w @ np.cos(p[:, 2])))
        mean = np.array([float(w @ p[:, 0]), float(w @ p[:, 1]), yaw])
        d = p - mean
        d[:, 2] = (d[:, 2] + np.pi) % (2.0 * np.pi) - np.pi
        self.pose = mean
        self.covariance = (d * w[:, None]).T @ d
