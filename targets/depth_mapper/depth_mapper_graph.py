"""A planar pose graph and its least-squares solution (Gauss-Newton).

Nodes are keyframe poses ``[x, y, yaw]`` in ``map``; an edge says where keyframe ``j`` lies in
keyframe ``i``'s frame, with an information matrix (Lu & Milios 1997; Grisetti et al. 2010,
"A tutorial on graph-based SLAM"). The first node is held where it is (it fixes the map frame:
the robot's start). Graphs here have a few hundred nodes, so the normal equations are solved
densely.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from depth_mapper_geometry import between, wrap

FloatArray = npt.NDArray[np.float64]

ANCHOR_INFORMATION = 1e9  # holds the first node


@dataclass
class Edge:
    """A relative pose measurement between two keyframes.

    Attributes:
        i: index of the keyframe the measurement is expressed in.
        j: index of the other keyframe.
        measurement: ``[x, y, yaw]`` of ``j`` in ``i``'s frame.
        information: 3 x 3 inverse covariance of the measurement, in ``i``'s frame.
        loop: whether it closes a loop (else it links consecutive keyframes).
    """

    i: int
    j: int
    measurement: FloatArray
    information: FloatArray
    loop: bool = False


def edge_error(pose_i: FloatArray, pose_j: FloatArray, measurement: FloatArray) -> FloatArray:
    """The residual of one edge: where ``j`` is seen from ``i``, minus the measurement."""
    rel = between(pose_i, pose_j)
    c, s = math.cos(measurement[2]), math.sin(measurement[2])
    dx, dy = rel[0] - measurement[0], rel[1] - measurement[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap(float(rel[2] - measurement[2]))])


def _jacobians(pose_i: FloatArray, pose_j: FloatArray, measurement: FloatArray
               ) -> tuple[FloatArray, FloatArray]:
    ci, si = math.cos(pose_i[2]), math.sin(pose_i[2])
    a = pose_i[2] + measurement[2]
    ca, sa = math.cos(a), math.sin(a)
    m = np.array([[ca, sa], [-sa, ca]])  # R(-(yaw_i + yaw_z))
    cz, sz = math.cos(measurement[2]), math.sin(measurement[2])
    rz_t = np.array([[cz, sz], [-sz, cz]])
    dt = pose_j[:2] - pose_i[:2]
    d_ri_t = np.array([[-si, ci], [-ci, -si]])  # d R(yaw_i)^T / d yaw_i
    jac_i = np.zeros((3, 3))
    jac_j = np.zeros((3, 3))
    jac_i[:2, :2] = -m
    jac_i[:2, 2] = rz_t @ d_ri_t @ dt
    jac_i[2, 2] = -1.0
    jac_j[:2, :2] = m
    jac_j[2, 2] = 1.0
    return jac_i, jac_j


def optimize(poses: FloatArray, edges: list[Edge], iterations: int = 10,
             tolerance: float = 1e-6) -> FloatArray:
    """The poses ``(k, 3)`` that best satisfy the edges, the first held fixed.

    Returns:
        a new array; the input is not changed.
    """
    x = np.array(poses, dtype=np.float64, copy=True)
    k = x.shape[0]
    if k < 2 or not edges:
        return x
    for _ in range(iterations):
        h = np.zeros((3 * k, 3 * k))
        g = np.zeros(3 * k)
        for edge in edges:
            i, j = edge.i, edge.j
            e = edge_error(x[i], x[j], edge.measurement)
            jac_i, jac_j = _jacobians(x[i], x[j], edge.measurement)
            omega = edge.information
            si, sj = slice(3 * i, 3 * i + 3), slice(3 * j, 3 * j + 3)
            h[si, si] += jac_i.T @ omega @ jac_i
            h[si, sj] += jac_i.T @ omega @ jac_j
            h[sj, si] += jac_j.T @ omega @ jac_i
            h[sj, sj] += jac_j.T @ omega @ jac_j
            g[si] += jac_i.T @ omega @ e
            g[sj] += jac_j.T @ omega @ e
        h[:3, :3] += np.eye(3) * ANCHOR_INFORMATION
        try:
            step = -np.linalg.solve(h, g)
        except np.linalg.LinAlgError:
            break
        x += step.reshape(k, 3)
        x[:, 2] = (x[:, 2] + math.pi) % (2.0 * math.pi) - math.pi
        if float(np.max(np.abs(step))) < tolerance:
            break
    return x


def edge_information(yaw_j: float, information: FloatArray) -> FloatArray:
    """An edge's information from that of pose ``j`` in ``map`` axes (``x, y, yaw``).

    The edge residual's position part is expressed in ``j``'s axes (``edge_error``), so the
    position block is turned by ``j``'s heading.
    """
    c, s = math.cos(yaw_j), math.sin(yaw_j)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # j's axes -> map axes
    out: FloatArray = rot.T @ information @ rot
    return out
