"""Scan-to-map matching by Gauss-Newton on a continuous distance field (LaMa's loc2d).

Pedrosa, Pereira, Lau: "Efficient localization based on scan matching with a continuous
likelihood field" (ICARSC 2017), as implemented in LaMa's ``Loc2D``: the cost of a pose is the
sum over the scan's end points of the (robustified) squared distance from each point, placed in
the map by the pose, to the nearest obstacle. The distance field is interpolated bilinearly
between cell centres, which makes it continuous with an analytic gradient, and truncated at
``max_distance`` (LaMa's ``l2_max``): a point farther than that from every obstacle has no
gradient and no say. Each iteration solves the normal equations ``H dx = -g`` with Cauchy
weights (iteratively reweighted least squares, Hartley & Zisserman A6.8), backtracking when a
step does not lower the cost. The covariance of the result is ``s^2 H^-1`` with ``s^2`` the
weighted residual variance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from planar_geometry import Pose, wrap_angle
from planar_map import GridMap, distance_field

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class MatcherConfig:
    """Gauss-Newton settings.

    Attributes:
        max_distance: distance field truncation (m; LaMa's l2_max).
        robust_scale: Cauchy scale c (m): a residual of c weighs half as much as 0.
        max_iterations: Gauss-Newton iterations per scan.
        tolerance: stop when a step moves less than this (m, and rad).
        min_points: fewer points inside the field than this: no match.
    """

    max_distance: float = 0.5
    robust_scale: float = 0.1
    max_iterations: int = 20
    tolerance: float = 1e-4
    min_points: int = 20


@dataclass(frozen=True)
class MatchResult:
    """One scan's match.

    Attributes:
        pose: the optimized pose (the initial one when ``ok`` is False).
        covariance: 3 x 3 (x, y, yaw); None when ``ok`` is False.
        ok: whether enough points constrained the pose and H was invertible.
        iterations: Gauss-Newton iterations run.
        points: end points inside the field at the result.
        rms: weighted RMS residual at the result (m).
    """

    pose: Pose
    covariance: FloatArray | None
    ok: bool
    iterations: int
    points: int
    rms: float


class DistanceMap:
    """The truncated distance field of a map, sampled bilinearly with its gradient.

    Derived from the map only: a cache, rebuilt when the map changes.
    """

    def __init__(self, grid: GridMap, max_distance: float) -> None:
        self.grid = grid
        self.max_distance = max_distance
        self.field = distance_field(grid.occupied(), grid.resolution, max_distance).astype(
            np.float64)

    def sample(self, x: FloatArray, y: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Distance and its gradient (d, dd/dx, dd/dy) at map points; off the map:
        ``max_distance`` with no gradient."""
        g = self.grid
        u = (x - g.origin_x) / g.resolution - 0.5  # in cells, 0 at the first cell's centre
        v = (y - g.origin_y) / g.resolution - 0.5
        inside = (u >= 0) & (u < g.width - 1) & (v >= 0) & (v < g.height - 1)
        u = np.where(inside, u, 0.0)
        v = np.where(inside, v, 0.0)
        i = np.floor(u).astype(np.int64)
        j = np.floor(v).astype(np.int64)
        fu, fv = u - i, v - j
        f = self.field
        d00, d10 = f[j, i], f[j, i + 1]
        d01, d11 = f[j + 1, i], f[j + 1, i + 1]
        d = (1 - fu) * (1 - fv) * d00 + fu * (1 - fv) * d10 + (1 - fu) * fv * d01 + fu * fv * d11
        gx = ((1 - fv) * (d10 - d00) + fv * (d11 - d01)) / g.resolution
        gy = ((1 - fu) * (d01 - d00) + fu * (d11 - d10)) / g.resolution
        d = np.where(inside, d, self.max_distance)
        return d, np.where(inside, gx, 0.0), np.where(inside, gy, 0.0)


def _cauchy_cost(r: FloatArray, c: float) -> float:
    return float(0.5 * c * c * np.log1p((r / c) ** 2).sum())


def match(distance: DistanceMap, px: FloatArray, py: FloatArray, initial: Pose,
          config: MatcherConfig) -> MatchResult:
    """Align points ``(px, py)`` (base_link) to the map, starting at pose ``initial``."""
    c = config.robust_scale
    pose = np.array(initial, dtype=np.float64)
    cost = math.inf
    iterations = 0
    for iterations in range(1, config.max_iterations + 1):
        cos, sin = math.cos(pose[2]), math.sin(pose[2])
        wx = pose[0] + cos * px - sin * py
        wy = pose[1] + sin * px + cos * py
        r, gx, gy = distance.sample(wx, wy)
        if not math.isfinite(cost):
            cost = _cauchy_cost(r, c)
        live = r < distance.max_distance
        if int(live.sum()) < config.min_points:
            return MatchResult(initial, None, False, iterations, int(live.sum()), 0.0)
        w = np.where(live, 1.0 / (1.0 + (r / c) ** 2), 0.0)
        # d(world point)/d(yaw) = (-sin px - cos py, cos px - sin py)
        jt = gx * (-sin * px - cos * py) + gy * (cos * px - sin * py)
        jac = np.column_stack([gx, gy, jt])
        hessian = (jac * w[:, None]).T @ jac
        gradient = jac.T @ (w * r)
        try:
            step = -np.linalg.solve(hessian, gradient)
        except np.linalg.LinAlgError:
            return MatchResult(initial, None, False, iterations, int(live.sum()), 0.0)
        # Backtrack until the (robust) cost goes down.
        for _ in range(6):
            trial = pose + step
            ct, st = math.cos(trial[2]), math.sin(trial[2])
            rt, _, _ = distance.sample(trial[0] + ct * px - st * py,
                                       trial[1] + st * px + ct * py)
            trial_cost = _cauchy_cost(rt, c)
            if trial_cost <= cost:
                break
            step = step / 2.0
        else:
            break  # no step lowers the cost: at the minimum (to the field's resolution)
        pose = trial
        cost = trial_cost
        if math.hypot(step[0], step[1]) < config.tolerance and abs(step[2]) < config.tolerance:
            break
    # The covariance at the result.
    cos, sin = math.cos(pose[2]), math.sin(pose[2])
    r, gx, gy = distance.sample(pose[0] + cos * px - sin * py, pose[1] + sin * px + cos * py)
    live = r < distance.max_distance
    n = int(live.sum())
    if n < config.min_points:
        return MatchResult(initial, None, False, iterations, n, 0.0)
    w = np.where(live, 1.0 / (1.0 + (r / c) ** 2), 0.0)
    jt = gx * (-sin * px - cos * py) + gy * (cos * px - sin * py)
    jac = np.column_stack([gx, gy, jt])
    hessian = (jac * w[:, None]).T @ jac
    if np.linalg.cond(hessian) > 1e9:
        return MatchResult(initial, None, False, iterations, n, 0.0)
    s2 = float((w * r * r).sum() / max(n - 3, 1))
    covariance = s2 * np.linalg.inv(hessian)
    rms = math.sqrt(float((w * r * r).sum() / max(float(w.sum()), 1e-12)))
    result: Pose = (float(pose[0]), float(pose[1]), wrap_angle(float(pose[2])))
    return MatchResult(result, covariance, True, iterations, n, rms)
