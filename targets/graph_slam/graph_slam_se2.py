"""Rigid motions in the plane, SE(2): poses as ``(x, y, yaw)`` arrays, composed and inverted.

A pose ``a`` maps points of its own frame into its parent frame; ``compose(a, b)`` is ``a ⊕ b``
(``b`` expressed in ``a``'s frame), ``between(a, b)`` is ``a⁻¹ ⊕ b``, the motion from ``a``
to ``b`` seen from ``a`` (the measurement of a pose-graph edge).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def wrap_angle(angle: float) -> float:
    """``angle`` wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def wrap_angles(angles: FloatArray) -> FloatArray:
    """Element-wise ``wrap_angle``."""
    return np.asarray((angles + np.pi) % (2.0 * np.pi) - np.pi, dtype=np.float64)


def pose(x: float, y: float, yaw: float) -> FloatArray:
    """A pose array with its yaw wrapped."""
    return np.array([x, y, wrap_angle(yaw)], dtype=np.float64)


def compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a ⊕ b``: the pose ``b`` (given in frame ``a``) in ``a``'s parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1],
                     wrap_angle(float(a[2] + b[2]))], dtype=np.float64)


def inverse(a: FloatArray) -> FloatArray:
    """``a⁻¹``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([-c * a[0] - s * a[1], s * a[0] - c * a[1], wrap_angle(float(-a[2]))],
                    dtype=np.float64)


def between(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a⁻¹ ⊕ b``: where ``b`` is as seen from ``a``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = float(b[0] - a[0]), float(b[1] - a[1])
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap_angle(float(b[2] - a[2]))],
                    dtype=np.float64)


def transform_points(p: FloatArray, points: npt.NDArray[np.floating]) -> FloatArray:
    """Points ``(n, 2)`` of frame ``p`` in ``p``'s parent frame (float64)."""
    c, s = math.cos(p[2]), math.sin(p[2])
    pts = np.asarray(points, dtype=np.float64)
    out = np.empty_like(pts)
    out[:, 0] = p[0] + c * pts[:, 0] - s * pts[:, 1]
    out[:, 1] = p[1] + s * pts[:, 0] + c * pts[:, 1]
    return out
