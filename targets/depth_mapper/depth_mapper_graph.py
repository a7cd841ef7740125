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


def optimize(poses: FloatArray, edges: list[Edge], iterations: int = 10,
             tolerance: float = 1e-5) -> FloatArray:
    """The poses ``(k, 3)`` that best satisfy the edges, the first held fixed.

    Returns:
        a new array; the input is not changed.
    """
    x = np.array(poses, dtype=np.float64, copy=True)
    k = x.shape[0]
    if k < 2 or not edges:
        return x
    ii = np.array([e.i for e in edges])
    jj = np.array([e.j for e in edges])
    z = np.array([e.measurement for e in edges], dtype=np.float64)
    omega = np.array([e.information for e in edges], dtype=np.float64)
    offsets = np.arange(3)
    base = {'i': 3 * ii, 'j': 3 * jj}
    size = 3 * k
    for _ in range(iterations):
        e, jac = batch_errors(x[ii], x[jj], z)
        flat_index = []
        flat_value = []
        g = np.zeros(size)
        for a in ('i', 'j'):
            ja_t_omega = np.einsum('nba,nbc->nac', jac[a], omega)
            rows = base[a][:, None] + offsets[None, :]
            g += np.bincount(rows.ravel(), weights=np.einsum('nac,nc->na', ja_t_omega,
                                                             e).ravel(), minlength=size)
            for b in ('i', 'j'):
                block = np.einsum('nac,ncd->nad', ja_t_omega, jac[b])
                cols = base[b][:, None] + offsets[None, :]
                flat_index.append((rows[:, :, None] * size + cols[:, None, :]).ravel())
                flat_value.append(block.ravel())
        h = np.bincount(np.concatenate(flat_index), weights=np.concatenate(flat_value),
                        minlength=size * size).reshape(size, size).astype(np.float64)
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


def batch_errors(pi: FloatArray, pj: FloatArray, z: FloatArray
                  ) -> tuple[FloatArray, dict[str, FloatArray]]:
    """``edge_error`` and its Jacobians for many edges at once: (n, 3), {i, j: (n, 3, 3)}."""
    ci, si = np.cos(pi[:, 2]), np.sin(pi[:, 2])
    dx, dy = pj[:, 0] - pi[:, 0], pj[:, 1] - pi[:, 1]
    rx, ry = ci * dx + si * dy, -si * dx + ci * dy  # j in i's frame
    cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
    ex, ey = rx - z[:, 0], ry - z[:, 1]
    e = np.stack([cz * ex + sz * ey, -sz * ex + cz * ey,
                  (pj[:, 2] - pi[:, 2] - z[:, 2] + math.pi) % (2.0 * math.pi) - math.pi],
                 axis=1)
    a = pi[:, 2] + z[:, 2]
    ca, sa = np.cos(a), np.sin(a)
    n = len(pi)
    jac_i = np.zeros((n, 3, 3))
    jac_j = np.zeros((n, 3, 3))
    # d(rx, ry)/d yaw_i = (ry, -rx); rotated into the measurement's frame by R(-yaw_z).
    jac_i[:, 0, 0], jac_i[:, 0, 1] = -ca, -sa
    jac_i[:, 1, 0], jac_i[:, 1, 1] = sa, -ca
    jac_i[:, 0, 2] = cz * ry + sz * (-rx)
    jac_i[:, 1, 2] = -sz * ry + cz * (-rx)
    jac_i[:, 2, 2] = -1.0
    jac_j[:, 0, 0], jac_j[:, 0, 1] = ca, sa
    jac_j[:, 1, 0], jac_j[:, 1, 1] = -sa, ca
    jac_j[:, 2, 2] = 1.0
    return e, {'i': jac_i, 'j': jac_j}


def edge_information(yaw_j: float, information: FloatArray) -> FloatArray:
    """An edge's information from that of pose ``j`` in ``map`` axes (``x, y, yaw``).

    The edge residual's position part is expressed in ``j``'s axes (``edge_error``), so the
    position block is turned by ``j``'s heading.
    """
    c, s = math.cos(yaw_j), math.sin(yaw_j)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # j's axes -> map axes
    out: FloatArray = rot.T @ information @ rot
    return out
