"""Planar poses: angle wrapping, composition, odometry deltas, quaternions, odometry lookup.

Poses are ``(x, y, yaw)`` tuples in metres and radians. No ROS here: the node converts
messages, the algorithm modules work on numbers.

Shared by targets/amcl and targets/lama_local, each of which links it into its folder
(targets/planar/README.md).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

Pose = tuple[float, float, float]
OdometrySample = tuple[int, float, float, float]  # (stamp in ns, x, y, yaw) in the odom frame


def wrap_angle(angle: float) -> float:
    """``angle`` wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def compose(a: Pose, b: Pose) -> Pose:
    """``a ⊕ b``: pose ``b``, given in the frame of ``a``, expressed in ``a``'s parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap_angle(a[2] + b[2]))


def relative(a: Pose, b: Pose) -> Pose:
    """``a⁻¹ ⊕ b``: pose ``b`` seen from pose ``a`` (both in the same frame)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return (c * dx + s * dy, -s * dx + c * dy, wrap_angle(b[2] - a[2]))


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """The rotation about z of a quaternion (roll and pitch are ignored: a planar robot)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation by ``yaw`` about z."""
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def odometry_at(history: deque[OdometrySample] | Sequence[OdometrySample],
                stamp_ns: int) -> Pose | None:
    """The odometry pose at ``stamp_ns``, interpolated between the two samples around it.

    A stamp before the oldest sample takes the oldest one, after the newest the newest one
    (odometry at 50 Hz against scans at 10 Hz: at most one period off). None when empty.
    """
    if not history:
        return None
    newest = history[-1]
    if stamp_ns >= newest[0]:
        return newest[1:]
    oldest = history[0]
    if stamp_ns <= oldest[0]:
        return oldest[1:]
    # Walk back from the newest: the stamp asked for is almost always among the last few.
    for k in range(len(history) - 2, -1, -1):
        before = history[k]
        if before[0] == stamp_ns:
            # A sample at the very stamp, as it is: the same pose as when it was the newest.
            # Interpolated at f = 0 it would pass through wrap_angle, which changes the last
            # bits of most angles, and the result would depend on whether later odometry had
            # arrived before the scan (it varies with delivery timing, and did in a handover).
            return before[1:]
        if before[0] <= stamp_ns:
            after = history[k + 1]
            span = after[0] - before[0]
            f = (stamp_ns - before[0]) / span if span > 0 else 1.0
            yaw = before[3] + f * wrap_angle(after[3] - before[3])
            return (before[1] + f * (after[1] - before[1]),
                    before[2] + f * (after[2] - before[2]), wrap_angle(yaw))
    return oldest[1:]
