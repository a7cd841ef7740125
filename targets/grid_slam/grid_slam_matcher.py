"""Gauss-Newton scan-to-map matching (Kohlbrecher et al. 2011, Sec. IV-B).

Find the pose xi = (x, y, theta) that best aligns the scan endpoints s_i (base_link) with the
map: minimise sum_i (1 - M(S_i(xi)))^2, where S_i(xi) is s_i moved by xi and M the
interpolated occupancy probability. Linearising M(S_i(xi + dxi)) gives the normal equations

    H dxi = sum_i [grad M(S_i) dS_i/dxi]^T (1 - M(S_i)),   H = sum_i J_i^T J_i,

solved a few times per level, from the coarsest map level to the finest, each level starting
from the previous one's result (coarse levels widen the basin of convergence).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from grid_slam_grid import FloatArray, GridGeometry, LogOdds, interpolate

MAX_ANGLE_STEP = 0.2  # rad per iteration, as hector_mapping limits it
MIN_CURVATURE = 1e-9  # H's diagonal below this: the map gives no information yet
CONVERGED_STEP = 1e-4  # m and rad: a smaller step changes nothing that matters


def transform(points: FloatArray, pose: npt.ArrayLike) -> FloatArray:
    """Base_link points (N, 2) in the map frame for the base_link pose (x, y, theta)."""
    x, y, theta = (float(v) for v in np.asarray(pose, dtype=np.float64))
    c, s = np.cos(theta), np.sin(theta)
    out = np.empty_like(points)
    out[:, 0] = x + c * points[:, 0] - s * points[:, 1]
    out[:, 1] = y + s * points[:, 0] + c * points[:, 1]
    return out


def gauss_newton_step(log_odds: LogOdds, geometry: GridGeometry, points: FloatArray,
                      pose: FloatArray) -> FloatArray | None:
    """One Gauss-Newton update of pose against one grid level; None when H is degenerate."""
    theta = float(pose[2])
    world = transform(points, pose)
    m, dm_dx, dm_dy = interpolate(log_odds, geometry, world)
    c, s = np.cos(theta), np.sin(theta)
    # d S_i / d theta for the rotation about the base_link origin.
    ds_dth_x = -s * points[:, 0] - c * points[:, 1]
    ds_dth_y = c * points[:, 0] - s * points[:, 1]
    jac = np.stack([dm_dx, dm_dy, dm_dx * ds_dth_x + dm_dy * ds_dth_y], axis=1)
    residual = 1.0 - m
    hessian = jac.T @ jac
    gradient = jac.T @ residual
    if hessian[0, 0] < MIN_CURVATURE or hessian[1, 1] < MIN_CURVATURE:
        return None
    try:
        step = np.linalg.solve(hessian, gradient)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(step)):
        return None
    step[2] = np.clip(step[2], -MAX_ANGLE_STEP, MAX_ANGLE_STEP)
    return np.asarray(pose + step, dtype=np.float64)


def match(levels: list[tuple[LogOdds, GridGeometry]], points: FloatArray, guess: FloatArray,
          iterations: list[int]) -> FloatArray:
    """Refine ``guess`` coarse to fine; ``levels`` and ``iterations`` are finest first."""
    pose = np.asarray(guess, dtype=np.float64).copy()
    for (log_odds, geometry), count in reversed(list(zip(levels, iterations, strict=True))):
        for _ in range(count):
            stepped = gauss_newton_step(log_odds, geometry, points, pose)
            if stepped is None:
                break
            converged = bool(np.all(np.abs(stepped - pose) < CONVERGED_STEP))
            pose = stepped
            if converged:
                break
    return pose
