"""A LaserScan's returns as points in ``base_link``."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from planar_geometry import Pose

FloatArray = npt.NDArray[np.float64]


def scan_points(ranges: npt.ArrayLike, angle_min: float, angle_increment: float,
                range_min: float, range_max: float, laser: Pose,
                max_beams: int = 0) -> tuple[FloatArray, FloatArray]:
    """End points ``(x, y)`` in base_link of the beams with a return.

    NaN (a dropout), +inf or anything at or beyond ``range_max`` (no return) and anything
    below ``range_min`` is left out. ``max_beams`` > 0 subsamples the beams evenly first.

    Raises:
        ValueError: the scan's geometry is unusable (no ranges, a zero or non-finite angle
            increment, non-finite limits).
    """
    r = np.asarray(ranges, dtype=np.float64).ravel()
    if r.size == 0:
        raise ValueError('no ranges')
    if not (math.isfinite(angle_min) and math.isfinite(angle_increment) and angle_increment != 0):
        raise ValueError(f'bad angles (angle_min {angle_min}, increment {angle_increment})')
    if not (math.isfinite(range_min) and math.isfinite(range_max) and range_max > 0):
        raise ValueError(f'bad range limits ({range_min}, {range_max})')
    index = np.arange(r.size)
    if 0 < max_beams < r.size:
        index = np.unique(np.round(np.linspace(0, r.size - 1, max_beams)).astype(np.int64))
    picked = r[index]
    with np.errstate(invalid='ignore'):
        usable = np.isfinite(picked) & (picked >= max(range_min, 0.0)) & (picked < range_max)
    index, picked = index[usable], picked[usable]
    angle = laser[2] + angle_min + index * angle_increment
    return laser[0] + picked * np.cos(angle), laser[1] + picked * np.sin(angle)
