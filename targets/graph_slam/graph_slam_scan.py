"""A laser scan as 2D points in ``base_link``: invalid beams dropped, malformed scans refused."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from graph_slam_se2 import FloatArray

PointArray = npt.NDArray[np.float32]


class ScanError(ValueError):
    """A scan that cannot be used (the message says why)."""


def scan_to_points(
    ranges: npt.ArrayLike,
    angle_min: float,
    angle_increment: float,
    range_min: float,
    range_max: float,
    laser_pose: FloatArray,
) -> PointArray:
    """The returns of one scan as points ``(n, 2)`` (float32) in the robot's base frame.

    Beams that are NaN, infinite or outside ``[range_min, range_max]`` carry no point (REP 117:
    +inf is "nothing within range", NaN a failed measurement); they are dropped, not mapped.

    Args:
        ranges: one range per beam (m).
        angle_min: angle of the first beam in the laser frame (rad).
        angle_increment: angle between beams (rad).
        range_min: the sensor's minimum range (m).
        range_max: the sensor's maximum range (m).
        laser_pose: the laser frame in the base frame, ``(x, y, yaw)``.

    Raises:
        ScanError: the scan's geometry is unusable (no beams, a zero or non-finite increment,
            non-finite limits).
    """
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    if r.size == 0:
        raise ScanError('the scan has no beams')
    if not (math.isfinite(angle_min) and math.isfinite(angle_increment)) or angle_increment == 0:
        raise ScanError(f'bad beam angles (angle_min {angle_min}, increment {angle_increment})')
    lo = range_min if math.isfinite(range_min) and range_min > 0 else 0.0
    hi = range_max if math.isfinite(range_max) and range_max > lo else math.inf
    with np.errstate(invalid='ignore'):
        valid = np.isfinite(r) & (r >= lo) & (r <= hi)
    idx = np.flatnonzero(valid)
    angles = laser_pose[2] + angle_min + idx * angle_increment
    d = r[idx]
    points = np.empty((idx.size, 2), dtype=np.float32)
    points[:, 0] = laser_pose[0] + d * np.cos(angles)
    points[:, 1] = laser_pose[1] + d * np.sin(angles)
    return points


def thin_points(points: PointArray, spacing: float) -> PointArray:
    """Drop points closer than about ``spacing`` to an already kept one (a scan's near-range
    returns are much denser than its far ones; matching should not weigh the nearest wall most).

    Keeps the first point of each ``spacing`` grid cell, in scan order: deterministic.
    """
    return points[thin_points_index(points, spacing)]


def thin_points_index(points: npt.NDArray[np.floating], spacing: float) -> npt.NDArray[np.int64]:
    """The indices ``thin_points`` keeps, ascending."""
    n = points.shape[0]
    if n == 0 or spacing <= 0:
        return np.arange(n, dtype=np.int64)
    cells = np.floor(np.asarray(points) / spacing).astype(np.int64)
    # one int64 per cell (rows of ~2 million cells each way are plenty at any spacing)
    key = (cells[:, 0] + (1 << 20)) * (1 << 21) + (cells[:, 1] + (1 << 20))
    _, first = np.unique(key, return_index=True)
    return np.sort(first).astype(np.int64)
