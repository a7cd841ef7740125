"""Frame-to-model point-to-plane ICP for a planar robot, with the odometry as a prior.

The robot moves on the floor, so the unknown is the planar pose ``[x, y, yaw]`` of
``base_link`` in ``map``. Each iteration pairs the frame's points (placed with the current
estimate) with the nearest model voxel point (``VoxelModel.nearest``) and minimises the
point-to-plane distances along the model normals (Chen & Medioni 1992; Low 2004 for the
linearisation), robustly weighted (Huber), plus the odometry prediction as a Gaussian prior:
one Gauss-Newton step on

    sum_i w_i (n_i . (T p_i - m_i))^2 / sigma_i^2 + (x - x_odom)^T Lambda (x - x_odom)

so that directions the geometry does not constrain (a long blank corridor) follow the
odometry instead of sliding freely.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from depth_mapper_geometry import rotate_directions, transform_points, wrap
from depth_mapper_model import VoxelModel

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class IcpSettings:
    """How the ICP pairs points and when it stops.

    Attributes:
        iterations: most Gauss-Newton iterations per frame.
        max_distance: pairs farther apart than this are rejected (m).
        max_normal_angle: pairs whose normals differ by more are rejected (rad).
        min_consistency: model voxels whose normals disagree more are not used as planes.
        huber: residual (m) beyond which a pair's weight falls off as 1/|r|.
        min_pairs: fewer accepted pairs and the frame is not tracked (odometry only).
        sigma_floor: smallest standard deviation a pair is trusted with (m): pairs are not
            independent (the model's voxels, its normals and the pose all err together), so
            hundreds of millimetre-precise points must not outvote the odometry in a direction
            the geometry hardly constrains.
        converged: stop when an update moves less than this (m, and rad).
        degenerate_sigma: directions of the pose that the geometry gives worse than this
            (m; yaw as the arc at ``lever`` metres) are left to the prior: a plane straight
            ahead says nothing about sliding along it, and a slightly tilted model normal
            would otherwise drag the pose sideways (solution remapping, Zhang, Kaess & Singh
            2016, "On degeneracy of optimization-based state estimation problems").
        lever: metres per radian when comparing yaw with position.
    """

    iterations: int = 8
    max_distance: float = 0.15
    max_normal_angle: float = math.radians(35.0)
    min_consistency: float = 0.5
    huber: float = 0.02
    min_pairs: int = 40
    sigma_floor: float = 0.02
    degenerate_sigma: float = 0.01
    lever: float = 1.0
    converged: float = 1e-4


@dataclass(frozen=True)
class IcpResult:
    """The outcome of one alignment.

    Attributes:
        pose: the estimated planar pose of ``base_link`` in ``map``.
        tracked: whether enough pairs were found (else ``pose`` is the prior).
        pairs: accepted pairs in the last iteration.
        iterations: iterations run.
        rms: root mean square point-to-plane residual of the accepted pairs (m).
        yaw_sigma: standard deviation of the yaw that the geometry alone gives (rad; inf when
            it does not constrain yaw), the marginal of the ICP's information without the
            prior.
        information: that information matrix (x, y, yaw in ``map`` axes).
    """

    pose: FloatArray
    tracked: bool
    pairs: int
    iterations: int
    rms: float
    yaw_sigma: float = math.inf
    information: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))


def align(model: VoxelModel, points: FloatArray, normals: FloatArray, sigmas: FloatArray,
          prior: FloatArray, prior_information: FloatArray, settings: IcpSettings
          ) -> IcpResult:
    """Align frame points to the model, starting from (and regularised by) the prior.

    Args:
        model: the voxel model in ``map``.
        points: the frame's points in ``base_link`` (n, 3).
        normals: their unit normals in ``base_link`` (n, 3).
        sigmas: their depth noise (m), for weighting (n,).
        prior: the predicted pose ``[x, y, yaw]`` (from odometry).
        prior_information: 3 x 3 inverse covariance of the prediction.
        settings: pairing and stopping rules.
    """
    pose = prior.astype(np.float64).copy()
    cos_limit = math.cos(settings.max_normal_angle)
    pairs = 0
    rms = 0.0
    iteration = 0
    geometry = np.zeros((3, 3))
    searched_at = pose.copy()
    neighbourhood = model.neighbourhood(transform_points(pose, points))
    # Points move less than this between searches (a point 5 m away moves 5 m per radian).
    reach = 0.5 * model.voxel_size
    for iteration in range(1, settings.iterations + 1):  # noqa: B007 - reported below
        world = transform_points(pose, points)
        moved = math.hypot(pose[0] - searched_at[0], pose[1] - searched_at[1]) + 5.0 * abs(
            wrap(float(pose[2] - searched_at[2])))
        if moved > reach:
            neighbourhood = model.neighbourhood(world)
            searched_at = pose.copy()
        index, dist = neighbourhood.nearest(world)
        ok = (index >= 0) & (dist < settings.max_distance)
        if int(ok.sum()) < settings.min_pairs:
            pairs = int(ok.sum())
            break
        idx = index[ok]
        model_normals, consistency = model.normals(idx)
        frame_normals = rotate_directions(pose[2], normals[ok])
        agree = np.einsum('ij,ij->i', model_normals, frame_normals) > cos_limit
        agree &= consistency >= settings.min_consistency
        # Horizontal-normal content: the floor constrains nothing of a planar pose.
        agree &= np.hypot(model_normals[:, 0], model_normals[:, 1]) > 0.3
        pairs = int(agree.sum())
        if pairs < settings.min_pairs:
            break
        p = world[ok][agree]
        local = points[ok][agree]
        m = model.means(idx[agree])
        n = model_normals[agree]
        r = np.einsum('ij,ij->i', n, p - m)
        sigma = np.maximum(sigmas[ok][agree], settings.sigma_floor)
        abs_r = np.abs(r)
        weight = np.where(abs_r <= settings.huber, 1.0, settings.huber / np.maximum(abs_r, 1e-12))
        weight = weight / sigma**2
        c, s = math.cos(pose[2]), math.sin(pose[2])
        # d(T p)/d yaw = (-s px - c py, c px - s py) for the local point p.
        dyaw = n[:, 0] * (-s * local[:, 0] - c * local[:, 1]) + n[:, 1] * (
            c * local[:, 0] - s * local[:, 1])
        jac = np.stack([n[:, 0], n[:, 1], dyaw], axis=1)
        h, g = well_constrained((jac * weight[:, None]).T @ jac, (jac * weight[:, None]).T @ r,
                                settings.degenerate_sigma, settings.lever)
        geometry = h.copy()
        dx = pose - prior
        dx[2] = wrap(float(dx[2]))
        h += prior_information
        g += prior_information @ dx
        try:
            step = -np.linalg.solve(h, g)
        except np.linalg.LinAlgError:
            break
        pose = pose + step
        pose[2] = wrap(float(pose[2]))
        rms = float(np.sqrt(np.mean(r**2)))
        if abs(step[0]) < settings.converged and abs(step[1]) < settings.converged and abs(
                step[2]) < settings.converged:
            break
    tracked = pairs >= settings.min_pairs
    return IcpResult(pose if tracked else prior.copy(), tracked, pairs, iteration, rms,
                     _marginal_yaw_sigma(geometry) if tracked else math.inf,
                     geometry if tracked else np.zeros((3, 3)))


def well_constrained(h: FloatArray, g: FloatArray, degenerate_sigma: float, lever: float
                     ) -> tuple[FloatArray, FloatArray]:
    """The normal equations ``(H, g)`` with their poorly constrained directions removed.

    Yaw is scaled by ``lever`` so that the eigen-directions compare like units; directions
    whose information is below ``1 / degenerate_sigma^2`` are projected out of both.
    """
    scale = np.array([1.0, 1.0, lever])
    hs = h / np.outer(scale, scale)
    gs = g / scale
    values, vectors = np.linalg.eigh(hs)
    good = values >= 1.0 / degenerate_sigma**2
    kept = vectors[:, good]
    hs = (kept * values[good]) @ kept.T
    gs = kept @ (kept.T @ gs)
    return hs * np.outer(scale, scale), gs * scale


def _marginal_yaw_sigma(information: FloatArray) -> float:
    """The yaw's standard deviation from a 3 x 3 information matrix (x, y, yaw)."""
    try:
        covariance = np.linalg.inv(information + np.eye(3) * 1e-9)
    except np.linalg.LinAlgError:
        return math.inf
    variance = float(covariance[2, 2])
    return math.sqrt(variance) if variance > 0 else math.inf
