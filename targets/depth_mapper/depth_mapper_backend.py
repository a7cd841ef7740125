"""Keyframes, the pose graph over them, loop closing and rebuilding the model.

As in ORB-SLAM2's local mapping and loop closing threads (Mur-Artal & Tardós 2017), here run
in line with tracking since it costs a few milliseconds per keyframe:

* every keyframe keeps its own cloud (``base_link``, one point per voxel), so the model can
  be rebuilt when the keyframe poses change;
* a new keyframe is registered against the few keyframes before it (``local_window``): the
  result, with the odometry as a prior, is the edge from the previous keyframe. Where the
  camera saw only the floor the edge is the odometry alone, with the odometry's (large)
  uncertainty, so a loop closure later bends the trajectory there and not elsewhere;
* it is also registered against old keyframes near its pose (a loop candidate, at least
  ``loop_min_gap`` keyframes back); a registration the geometry pins down in all three
  directions adds a loop edge; unless the keyframe poses already satisfy it, the graph is
  solved (``depth_mapper_graph``) and the model rebuilt from the keyframes at their new poses.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from depth_mapper_geometry import between, compose, wrap
from depth_mapper_graph import Edge, edge_error, edge_information, optimize
from depth_mapper_icp import IcpResult, IcpSettings, align
from depth_mapper_model import VoxelModel

F32 = npt.NDArray[np.float32]
FloatArray = npt.NDArray[np.float64]


class LoopClosure(enum.Enum):
    """What a loop search at a new keyframe came to."""

    NONE = 'none'  # no candidate, or none that registered well
    AGREED = 'agreed'  # a loop edge the keyframe poses already satisfied
    MOVED = 'moved'  # a loop edge that moved the keyframes: rebuild the model


@dataclass
class Keyframe:
    """One keyframe: when, where, and what it saw.

    Attributes:
        stamp_ns: the frame's stamp.
        pose: ``base_link`` in ``map`` (changed by loop closures).
        odom: the odometry pose at the frame (``odom`` frame), None without odometry.
        points: its points in ``base_link``, one per voxel (weighted means), (m, 3).
        normal_sums: their weighted sums of unit normals, (m, 3).
        weights: their summed weights (inverse depth variances), (m,).
    """

    stamp_ns: int
    pose: FloatArray
    odom: tuple[float, float, float] | None
    points: F32
    normal_sums: F32
    weights: F32


@dataclass(frozen=True)
class BackendSettings:
    """How keyframes are linked and loops found.

    Attributes:
        local_window: keyframes the new one is registered against for its edge.
        loop_min_gap: a loop candidate is at least this many keyframes old.
        loop_radius: and its pose within this distance (m)...
        loop_angle: ...and heading (rad) of the new keyframe's.
        loop_every: keyframes between loop searches after a closure.
        loop_max_sigma: a loop registration must give x, y (m) and yaw (rad / 10) this well.
        loop_max_rms: and fit this well (m).
        loop_min_pairs: with at least this many pairs.
        loop_agree_distance: a loop that the keyframe poses already agree with this well (m)...
        loop_agree_angle: ...and this well (rad) is added without solving the graph.
        track_sigma: standard deviations (x, y, yaw) below which a keyframe registration is
            not believed (its information is capped there): pairs are not independent.
        icp: the registrations' pairing rules.
    """

    local_window: int = 4
    loop_min_gap: int = 20
    loop_radius: float = 1.5
    loop_angle: float = math.radians(45.0)
    loop_every: int = 3
    loop_max_sigma: float = 0.02
    loop_max_rms: float = 0.02
    loop_min_pairs: int = 150
    loop_agree_distance: float = 0.01
    loop_agree_angle: float = 0.002
    track_sigma: tuple[float, float, float] = (0.01, 0.01, 0.002)
    icp: IcpSettings = field(default_factory=lambda: IcpSettings(max_distance=0.2,
                                                                 iterations=12))


def downsample(points: FloatArray, normal_sums: FloatArray, weights: FloatArray,
               voxel_size: float) -> tuple[F32, F32, F32]:
    """One weighted-mean point per voxel (in the points' own frame), normals and weights summed."""
    if points.shape[0] == 0:
        empty = np.zeros((0, 3), dtype=np.float32)
        return empty, empty.copy(), np.zeros(0, dtype=np.float32)
    model = VoxelModel(voxel_size)
    model.integrate(points, normal_sums, weights)
    return (model.means().astype(np.float32), model.normal_sums.astype(np.float32),
            model.counts.astype(np.float32))


def _window_model(keyframes: list[Keyframe], voxel_size: float) -> VoxelModel:
    model = VoxelModel(voxel_size)
    for kf in keyframes:
        integrate_keyframe(model, kf)
    return model


def _in_map(kf: Keyframe, pose: FloatArray) -> tuple[FloatArray, FloatArray]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    points = kf.points.astype(np.float64) @ rot.T + np.array([pose[0], pose[1], 0.0])
    normals = kf.normal_sums.astype(np.float64) @ rot.T
    return points, normals


def integrate_keyframe(model: VoxelModel, kf: Keyframe) -> None:
    """Fuse a keyframe's cloud into ``model`` at the keyframe's pose."""
    points, normals = _in_map(kf, kf.pose)
    model.integrate(points, normals, kf.weights.astype(np.float64))


def _register(model: VoxelModel, kf: Keyframe, start: FloatArray, prior_information: FloatArray,
              settings: IcpSettings, sigma_floor: float) -> IcpResult:
    """Align a keyframe's cloud (its voxels with a consistent, not vertical normal) to
    ``model`` from ``start``."""
    sums = kf.normal_sums.astype(np.float64)
    length = np.linalg.norm(sums, axis=1)
    usable = (length > 0.5 * kf.weights) & (np.hypot(sums[:, 0], sums[:, 1]) > 0.3 * length)
    normals = sums[usable] / length[usable, None]
    sigmas = np.full(int(usable.sum()), sigma_floor)
    return align(model, kf.points[usable].astype(np.float64), normals, sigmas, start,
                 prior_information, settings)


def _capped_information(information: FloatArray, sigma: tuple[float, float, float]
                       ) -> FloatArray:
    """Cap an information matrix at ``1 / sigma^2`` per axis (by scaling it down)."""
    cap = np.array([1.0 / v**2 for v in sigma])
    scale = float(np.min(cap / np.maximum(np.diag(information), 1e-12)))
    return information * min(1.0, scale)


class Backend:
    """The keyframes and the pose graph.

    Attributes (the state):
        keyframes: every keyframe, oldest first.
        edges: the graph's edges (``i`` < ``j``: indices into ``keyframes``).
        since_loop: keyframes since the last loop closure.
    """

    def __init__(self, settings: BackendSettings, voxel_size: float) -> None:
        self.settings = settings
        self.voxel_size = voxel_size
        self.keyframes: list[Keyframe] = []
        self.edges: list[Edge] = []
        self.since_loop = 0

    def add(self, kf: Keyframe, odom_delta: FloatArray | None,
            odom_information: FloatArray | None) -> None:
        """A new keyframe and the edge to the one before it.

        Args:
            kf: the keyframe, at the pose tracking gave it.
            odom_delta: the (corrected) odometry motion from the previous keyframe, in its
                frame; None without odometry.
            odom_information: the information of that motion.
        """
        self.keyframes.append(kf)
        self.since_loop += 1
        k = len(self.keyframes) - 1
        if k == 0:
            return
        previous = self.keyframes[k - 1]
        if odom_delta is not None and odom_information is not None:
            prior = compose(previous.pose, odom_delta)
            prior_info = edge_information(float(prior[2]), odom_information)
        else:
            prior = kf.pose.copy()
            prior_info = np.diag([1.0 / 0.1**2, 1.0 / 0.1**2, 1.0 / 0.1**2])
        window = self.keyframes[max(0, k - self.settings.local_window):k]
        result = _register(_window_model(window, self.voxel_size), kf, kf.pose, prior_info,
                           self.settings.icp, self.settings.icp.sigma_floor)
        if result.tracked:
            pose = result.pose
            information = _capped_information(result.information, self.settings.track_sigma)
            information = information + prior_info
        else:
            pose = prior
            information = prior_info
        measurement = between(previous.pose, pose)
        self.edges.append(Edge(k - 1, k, measurement,
                               edge_information(float(pose[2]), information)))

    def close_loop(self) -> LoopClosure:
        """Look for a loop at the newest keyframe; on one, add its edge and solve the graph.

        Returns:
            NONE, AGREED (an edge the poses already satisfied: nothing solved) or MOVED (the
            keyframe poses changed: the model must be rebuilt).
        """
        s = self.settings
        k = len(self.keyframes) - 1
        if k < s.loop_min_gap or self.since_loop < s.loop_every:
            return LoopClosure.NONE
        kf = self.keyframes[k]
        best, best_score = -1, math.inf
        for i in range(k - s.loop_min_gap + 1):
            other = self.keyframes[i]
            distance = math.hypot(other.pose[0] - kf.pose[0], other.pose[1] - kf.pose[1])
            turn = abs(wrap(float(other.pose[2] - kf.pose[2])))
            if distance <= s.loop_radius and turn <= s.loop_angle:
                score = distance + turn
                if score < best_score:
                    best, best_score = i, score
        if best < 0:
            return LoopClosure.NONE
        lo, hi = max(0, best - 2), min(k - s.loop_min_gap + 1, best + 3)
        model = _window_model(self.keyframes[lo:hi], self.voxel_size)
        weak = np.diag([1.0 / 0.3**2, 1.0 / 0.3**2, 1.0 / 0.1**2])
        result = _register(model, kf, kf.pose, weak, s.icp, s.icp.sigma_floor)
        if not result.tracked or result.pairs < s.loop_min_pairs or result.rms > s.loop_max_rms:
            return LoopClosure.NONE
        if not pins_pose(result.information, s.loop_max_sigma):
            return LoopClosure.NONE
        anchor = self.keyframes[best]
        information = _capped_information(result.information, s.track_sigma)
        edge = Edge(best, k, between(anchor.pose, result.pose),
                    edge_information(float(result.pose[2]), information), loop=True)
        self.edges.append(edge)
        self.since_loop = 0
        residual = edge_error(anchor.pose, kf.pose, edge.measurement)
        if math.hypot(residual[0], residual[1]) < s.loop_agree_distance and abs(
                residual[2]) < s.loop_agree_angle:
            return LoopClosure.AGREED  # the edge stays; there is nothing to solve
        poses = np.array([kf_.pose for kf_ in self.keyframes])
        solved = optimize(poses, self.edges)
        change = np.abs(solved - poses)
        change[:, 2] = np.abs((solved[:, 2] - poses[:, 2] + math.pi) % (2 * math.pi) - math.pi)
        if float(change[:, :2].max()) < 0.005 and float(change[:, 2].max()) < 0.001:
            return LoopClosure.AGREED
        for kf_, pose in zip(self.keyframes, solved, strict=True):
            kf_.pose = pose.copy()
        return LoopClosure.MOVED

    def rebuild(self, model: VoxelModel) -> None:
        """Refill ``model`` from every keyframe at its current pose."""
        clouds = [_in_map(kf, kf.pose) for kf in self.keyframes]
        model.rebuild([c[0] for c in clouds], [c[1] for c in clouds],
                      [kf.weights.astype(np.float64) for kf in self.keyframes])


def pins_pose(information: npt.NDArray[np.float64], max_sigma: float) -> bool:
    """Whether a fit's information pins x and y to ``max_sigma`` and yaw to a tenth of it.

    The registration projects out the directions the geometry does not constrain, so its
    information can be singular; inverting that gives garbage (negative variances that would
    read as zero). A singular or ill-conditioned matrix does not pin the pose.
    """
    if not np.all(np.isfinite(information)):
        return False
    eigenvalues = np.linalg.eigvalsh(information)
    if eigenvalues.min() <= 1e-9 * max(
            float(eigenvalues.max()), 1e-300):
        return False
    variances = np.diag(np.linalg.inv(information))
    if np.any(variances <= 0.0):
        return False
    sigmas = np.sqrt(variances)
    return bool(sigmas[0] <= max_sigma and sigmas[1] <= max_sigma
                and sigmas[2] <= max_sigma / 10.0)
