"""Planar poses (x, y, yaw) and the camera mount: the frames the depth mapper works in.

The robot moves on the floor, so ``base_link`` has three degrees of freedom in ``map``; the
camera is fixed on it (a static transform, given as parameters since there is no TF here).
Poses are ``numpy`` arrays ``[x, y, yaw]`` in metres and radians.
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]


def wrap(angle: float) -> float:
    """``angle`` wrapped to [-pi, pi)."""
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a ⊕ b``: pose ``b`` (given in ``a``'s frame) expressed in ``a``'s parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], wrap(a[2] + b[2])])


def between(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a⁻¹ ⊕ b``: pose ``b`` expressed in the frame of pose ``a`` (both in one frame)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap(b[2] - a[2])])


def interpolate(a: FloatArray, b: FloatArray, fraction: float) -> FloatArray:
    """The pose ``fraction`` of the way from ``a`` to ``b`` (yaw along the short way)."""
    out = a + fraction * (b - a)
    out[2] = wrap(a[2] + fraction * wrap(b[2] - a[2]))
    return np.asarray(out, dtype=np.float64)


def yaw_of_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rotation about z) of a quaternion."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def optical_to_base(points: npt.NDArray[np.float32], mount: tuple[float, float, float]
                    ) -> FloatArray:
    """Points ``(..., 3)`` in the optical frame (z forward, x right, y down) in ``base_link``.

    Args:
        points: optical-frame coordinates.
        mount: the optical frame's origin in ``base_link`` (x, y, z); its axes are fixed:
            base x = optical z, base y = -optical x, base z = -optical y (REP 103).
    """
    p = np.asarray(points, dtype=np.float64)
    out = np.empty(p.shape, dtype=np.float64)
    out[..., 0] = p[..., 2] + mount[0]
    out[..., 1] = -p[..., 0] + mount[1]
    out[..., 2] = -p[..., 1] + mount[2]
    return out


def optical_directions_to_base(vectors: FloatArray) -> FloatArray:
    """Directions (normals) ``(..., 3)`` from optical axes to ``base_link`` axes."""
    out = np.empty(vectors.shape, dtype=np.float64)
    out[..., 0] = vectors[..., 2]
    out[..., 1] = -vectors[..., 0]
    out[..., 2] = -vectors[..., 1]
    return out


def transform_points(pose: FloatArray, points: FloatArray) -> FloatArray:
    """``base_link`` points ``(n, 3)`` in ``map`` for the planar pose of ``base_link``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(points)
    out[:, 0] = pose[0] + c * points[:, 0] - s * points[:, 1]
    out[:, 1] = pose[1] + s * points[:, 0] + c * points[:, 1]
    out[:, 2] = points[:, 2]
    return out


def rotate_directions(yaw: float, vectors: FloatArray) -> FloatArray:
    """Directions ``(n, 3)`` rotated by ``yaw`` about z."""
    c, s = math.cos(yaw), math.sin(yaw)
    out = np.empty_like(vectors)
    out[:, 0] = c * vectors[:, 0] - s * vectors[:, 1]
    out[:, 1] = s * vectors[:, 0] + c * vectors[:, 1]
    out[:, 2] = vectors[:, 2]
    return out


def camera_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """Orientation (x, y, z, w) in ``map`` of the optical frame on a robot with heading ``yaw``.

    The optical frame is base_link rotated so that z looks forward, x right, y down: the
    rotation matrix columns are the optical axes in ``map``.
    """
    c, s = math.cos(yaw), math.sin(yaw)
    # Columns: optical x = -base y, optical y = -base z, optical z = base x (all in map).
    r = np.array([[s, 0.0, c],
                  [-c, 0.0, s],
                  [0.0, -1.0, 0.0]])
    return _quaternion_of_matrix(r)


def _quaternion_of_matrix(r: FloatArray) -> tuple[float, float, float, float]:
    trace = float(r[0, 0] + r[1, 1] + r[2, 2])
    if trace > 0.0:
        k = 2.0 * math.sqrt(trace + 1.0)
        return ((r[2, 1] - r[1, 2]) / k, (r[0, 2] - r[2, 0]) / k, (r[1, 0] - r[0, 1]) / k,
                0.25 * k)
    i = int(np.argmax(np.diag(r)))
    j, k_ = (i + 1) % 3, (i + 2) % 3
    t = 2.0 * math.sqrt(max(1e-12, 1.0 + r[i, i] - r[j, j] - r[k_, k_]))
    q = [0.0, 0.0, 0.0, 0.0]
    q[i] = 0.25 * t
    q[j] = (r[j, i] + r[i, j]) / t
    q[k_] = (r[k_, i] + r[i, k_]) / t
    q[3] = (r[k_, j] - r[j, k_]) / t
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))
