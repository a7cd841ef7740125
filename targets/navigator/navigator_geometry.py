"""Planar rigid transforms and the conversions the navigator needs (no ROS, no TF).

Poses are ``(x, y, yaw)`` in metres and radians; ``compose(a, b)`` is ``a * b`` in SE(2), so
``compose(map_from_odom, odom_from_base)`` is the robot's pose in ``map``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Pose2D:
    """A planar pose (or the transform it stands for)."""

    x: float
    y: float
    yaw: float


IDENTITY = Pose2D(0.0, 0.0, 0.0)


def wrap(angle: float) -> float:
    """``angle`` wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def compose(a: Pose2D, b: Pose2D) -> Pose2D:
    """The transform ``a * b`` (b expressed in a's frame, taken to a's parent frame)."""
    c, s = math.cos(a.yaw), math.sin(a.yaw)
    return Pose2D(a.x + c * b.x - s * b.y, a.y + s * b.x + c * b.y, wrap(a.yaw + b.yaw))


def inverse(a: Pose2D) -> Pose2D:
    """The inverse transform of ``a``."""
    c, s = math.cos(a.yaw), math.sin(a.yaw)
    return Pose2D(-c * a.x - s * a.y, s * a.x - c * a.y, wrap(-a.yaw))


def interpolate(a: Pose2D, b: Pose2D, fraction: float) -> Pose2D:
    """The pose ``fraction`` of the way from a to b (yaw along the shorter arc)."""
    return Pose2D(a.x + fraction * (b.x - a.x), a.y + fraction * (b.y - a.y),
                  wrap(a.yaw + fraction * wrap(b.yaw - a.yaw)))


def transform_points(pose: Pose2D, points: FloatArray) -> FloatArray:
    """Points ``(N, 2)`` given in pose's frame, expressed in its parent frame."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    rot = np.array([[c, -s], [s, c]])
    return np.asarray(points @ rot.T + np.array([pose.x, pose.y]), dtype=np.float64)


def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rotation about z) of a quaternion; NaN in, NaN out."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def quaternion_from_yaw(yaw: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation by yaw about z."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def path_length(points: FloatArray) -> float:
    """Length of a polyline ``(N, 2)`` (0 for fewer than two points)."""
    if len(points) < 2:
        return 0.0
    return float(np.hypot(*np.diff(points, axis=0).T).sum())
