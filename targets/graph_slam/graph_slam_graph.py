"""The pose graph: keyframes (nodes) with their scans, edges with information matrices, and
its optimisation by Gauss-Newton on SE(2) (Grisetti et al., "A tutorial on graph-based SLAM",
2010).

Each edge ``i → j`` measures ``z = x_i⁻¹ ⊕ x_j`` with information ``Ω``; the optimiser
minimises ``Σ eᵀ Ω e`` with ``e = t2v(Z⁻¹ X_i⁻¹ X_j)``, the first keyframe held fixed (the
gauge). The normal equations are assembled in one vectorised pass and solved densely: the
venv has no scipy, and a graph of a few hundred keyframes (a 1000 x 1000 system) solves in
milliseconds; the cost grows with the cube of the keyframe count.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

import numpy as np
import numpy.typing as npt

from graph_slam_se2 import FloatArray, wrap_angles


class EdgeKind(Enum):
    """Where an edge's measurement came from."""

    ODOMETRY = 'odometry'  # wheel odometry alone (scan matching failed or is off)
    SCAN_MATCH = 'scan_match'  # odometry refined by matching to the recent keyframes
    LOOP = 'loop'  # a verified loop closure to a keyframe visited long before


@dataclass
class Keyframe:
    """A node of the graph.

    Attributes:
        stamp_ns: the scan's header stamp (ns).
        pose: the current estimate ``(x, y, yaw)`` in the map frame (changes on optimisation).
        points: the scan's returns in the robot's base frame, float32 ``(n, 2)``.
        travelled: distance driven from the first keyframe to this one (m), by the estimates at
            creation; tells a loop (long way round) from a neighbour.
    """

    stamp_ns: int
    pose: FloatArray
    points: npt.NDArray[np.float32]
    travelled: float


@dataclass
class Edge:
    """A constraint between keyframes ``source`` and ``target``.

    Attributes:
        source: index of the keyframe the measurement is seen from.
        target: index of the other keyframe.
        measurement: ``x_source⁻¹ ⊕ x_target`` as measured.
        information: 3 x 3 inverse covariance of the measurement.
        kind: what produced it.
        score: match score (0..1) for matched edges, 0 for odometry.
    """

    source: int
    target: int
    measurement: FloatArray
    information: FloatArray
    kind: EdgeKind
    score: float = 0.0


@dataclass(frozen=True)
class OptimisationResult:
    """What one optimisation did (for logs and diagnostics; never state)."""

    iterations: int
    initial_error: float
    final_error: float
    max_pose_change: float  # largest translation of a keyframe (m)
    max_yaw_change: float  # largest rotation of a keyframe (rad)


def edge_errors(poses: FloatArray, edges: list[Edge]) -> FloatArray:
    """``e`` per edge ``(m, 3)`` for poses ``(n, 3)``."""
    if not edges:
        return np.zeros((0, 3))
    src = np.array([e.source for e in edges])
    dst = np.array([e.target for e in edges])
    z = np.array([e.measurement for e in edges])
    return _errors(poses, src, dst, z)


def _errors(poses: FloatArray, src: npt.NDArray[np.int64], dst: npt.NDArray[np.int64],
            z: FloatArray) -> FloatArray:
    xi, xj = poses[src], poses[dst]
    ci, si = np.cos(xi[:, 2]), np.sin(xi[:, 2])
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
    # R_i^T (t_j - t_i) - t_z, then rotated by R_z^T
    lx = ci * dx + si * dy - z[:, 0]
    ly = -si * dx + ci * dy - z[:, 1]
    e = np.empty_like(z)
    e[:, 0] = cz * lx + sz * ly
    e[:, 1] = -sz * lx + cz * ly
    e[:, 2] = wrap_angles(xj[:, 2] - xi[:, 2] - z[:, 2])
    return e


def chi2(poses: FloatArray, edges: list[Edge]) -> FloatArray:
    """``eᵀ Ω e`` per edge."""
    if not edges:
        return np.zeros(0)
    e = edge_errors(poses, edges)
    info = np.array([edge.information for edge in edges])
    return np.asarray(np.einsum('mi,mij,mj->m', e, info, e), dtype=np.float64)


def optimise(poses: FloatArray, edges: list[Edge], iterations: int = 10,
             tolerance: float = 1e-5) -> tuple[FloatArray, OptimisationResult]:
    """Gauss-Newton on the pose graph; keyframe 0 is held fixed.

    Args:
        poses: current estimates ``(n, 3)``.
        edges: the constraints (indices into ``poses``).
        iterations: at most this many linearisations (bounds the time spent).
        tolerance: stop when no pose moves more than this (m, rad).

    Returns:
        The optimised poses (a new array) and what happened.
    """
    x = np.array(poses, dtype=np.float64)
    n = x.shape[0]
    if n < 2 or not edges:
        return x, OptimisationResult(0, 0.0, 0.0, 0.0, 0.0)
    src = np.array([e.source for e in edges], dtype=np.int64)
    dst = np.array([e.target for e in edges], dtype=np.int64)
    z = np.array([e.measurement for e in edges], dtype=np.float64)
    info = np.array([e.information for e in edges], dtype=np.float64)
    m = len(edges)
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    rz_t = np.zeros((m, 2, 2))  # R_z^T
    rz_t[:, 0, 0], rz_t[:, 0, 1], rz_t[:, 1, 0], rz_t[:, 1, 1] = cz, sz, -sz, cz
    # block (a, b) of H lands at rows 3a..3a+2, cols 3b..3b+2
    k3 = np.arange(3)
    initial = final = _total(x, src, dst, z, info)
    done = 0
    for iteration in range(1, iterations + 1):
        done = iteration
        e = _errors(x, src, dst, z)
        xi, xj = x[src], x[dst]
        ci, si = np.cos(xi[:, 2]), np.sin(xi[:, 2])
        dx, dy = xj[:, 0] - xi[:, 0], xj[:, 1] - xi[:, 1]
        ri_t = np.zeros((m, 2, 2))
        ri_t[:, 0, 0], ri_t[:, 0, 1], ri_t[:, 1, 0], ri_t[:, 1, 1] = ci, si, -si, ci
        dri_t = np.zeros((m, 2, 2))  # d(R_i^T)/d(theta_i)
        dri_t[:, 0, 0], dri_t[:, 0, 1], dri_t[:, 1, 0], dri_t[:, 1, 1] = -si, ci, -ci, -si
        a = np.zeros((m, 3, 3))
        b = np.zeros((m, 3, 3))
        rr = rz_t @ ri_t
        a[:, :2, :2] = -rr
        a[:, :2, 2] = (rz_t @ dri_t @ np.stack([dx, dy], axis=1)[:, :, None])[:, :, 0]
        a[:, 2, 2] = -1.0
        b[:, :2, :2] = rr
        b[:, 2, 2] = 1.0
        at_o = np.transpose(a, (0, 2, 1)) @ info
        bt_o = np.transpose(b, (0, 2, 1)) @ info
        h = np.zeros((3 * n, 3 * n))
        g = np.zeros(3 * n)
        rows_i = (3 * src)[:, None] + k3[None, :]
        rows_j = (3 * dst)[:, None] + k3[None, :]
        for rows, cols, block in ((rows_i, rows_i, at_o @ a), (rows_i, rows_j, at_o @ b),
                                  (rows_j, rows_i, bt_o @ a), (rows_j, rows_j, bt_o @ b)):
            np.add.at(h, (rows[:, :, None], cols[:, None, :]), block)
        np.add.at(g, rows_i, (at_o @ e[:, :, None])[:, :, 0])
        np.add.at(g, rows_j, (bt_o @ e[:, :, None])[:, :, 0])
        # Fix keyframe 0: solve for the others only.
        step = np.linalg.solve(h[3:, 3:], -g[3:])
        x[1:, 0] += step[0::3]
        x[1:, 1] += step[1::3]
        x[1:, 2] = wrap_angles(x[1:, 2] + step[2::3])
        final = _total(x, src, dst, z, info)
        if float(np.abs(step).max()) < tolerance:
            break
    moved = np.hypot(x[:, 0] - poses[:, 0], x[:, 1] - poses[:, 1])
    turned = np.abs(wrap_angles(x[:, 2] - poses[:, 2]))
    return x, OptimisationResult(done, initial, final, float(moved.max()), float(turned.max()))


def _total(x: FloatArray, src: npt.NDArray[np.int64], dst: npt.NDArray[np.int64], z: FloatArray,
           info: FloatArray) -> float:
    e = _errors(x, src, dst, z)
    return float(np.einsum('mi,mij,mj->', e, info, e))


def information(sigma_xy: float, sigma_yaw: float) -> FloatArray:
    """A diagonal information matrix from standard deviations (m, rad)."""
    return np.diag([1.0 / sigma_xy**2, 1.0 / sigma_xy**2, 1.0 / sigma_yaw**2])


def path_length(a: FloatArray, b: FloatArray) -> float:
    """Straight-line distance between two poses' positions (m)."""
    return math.hypot(float(b[0] - a[0]), float(b[1] - a[1]))
