"""LaserScan ranges to 2D points in base_link (plain numpy, no ROS).

The scan arrives in ``base_scan``; the lidar is mounted at a fixed offset in ``base_link``
(there is no TF here, as on a robot whose URDF never changes). Beams that carry no measurement
are dropped, as hector_mapping does: NaN (a dropout), +inf (no return within range) and
anything outside ``[min_range, max_range]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class LaserMount:
    """Where the lidar sits in base_link (a planar pose; its height does not matter in 2D)."""

    x: float = -0.064
    y: float = 0.0
    yaw: float = 0.0


class ScanError(ValueError):
    """A LaserScan whose fields cannot describe a scan (the message says what is wrong)."""


def scan_to_points(ranges: npt.ArrayLike, angle_min: float, angle_increment: float,
                   min_range: float, max_range: float,
                   mount: LaserMount) -> FloatArray:
    """The valid beams of one scan as (N, 2) endpoints in base_link.

    Args:
        ranges: one range per beam (m); NaN and inf are allowed and dropped.
        angle_min: angle of the first beam in the laser frame (rad).
        angle_increment: angle between beams (rad).
        min_range: shortest range kept (m).
        max_range: longest range kept (m).
        mount: the laser's pose in base_link.

    Returns:
        float64 array (N, 2); N may be 0.

    Raises:
        ScanError: the angles are not finite or the increment is zero.
    """
    if not (math.isfinite(angle_min) and math.isfinite(angle_increment)) or angle_increment == 0:
        msg = f'bad beam angles (angle_min={angle_min}, angle_increment={angle_increment})'
        raise ScanError(msg)
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    angles = mount.yaw + angle_min + angle_increment * np.arange(r.size)
    with np.errstate(invalid='ignore'):
        keep = np.isfinite(r) & (r >= min_range) & (r <= max_range)
    r, angles = r[keep], angles[keep]
    points = np.empty((r.size, 2))
    points[:, 0] = mount.x + r * np.cos(angles)
    points[:, 1] = mount.y + r * np.sin(angles)
    return points
