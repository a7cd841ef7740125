"""The depth mapper without ROS: odometry in, depth frames in, pose and voxel model out.

Per depth frame (as ORB-SLAM2's tracking thread does per image, with wheel odometry standing in
for its constant-velocity motion model):

1. predict the pose from the odometry moved since the last frame (interpolated at the frame's
   stamp; a frame waits, in ``pending``, until odometry at or after its stamp has arrived);
2. align the frame to the model, point-to-plane ICP seeded and regularised by the prediction
   (and, if that finds too few pairs, once more with a wider pairing: relocalisation);
3. if the robot has moved far enough from the last keyframe, make this frame a keyframe: link
   it into the pose graph, fuse its cloud into the voxel model, look for a loop
   (``depth_mapper_backend``).

Every state change comes from ``add_odometry``/``add_frame`` and depends only on their
arguments (stamps from message headers), so feeding the same messages in the same order gives
the same state. There is no randomness.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from depth_mapper_backend import (
    Backend,
    BackendSettings,
    Keyframe,
    LoopClosure,
    downsample,
    integrate_keyframe,
)
from depth_mapper_calibration import HeadingCalibration
from depth_mapper_cloud import organised_normals, valid_mask
from depth_mapper_geometry import (
    between,
    compose,
    interpolate,
    optical_directions_to_base,
    optical_to_base,
    wrap,
)
from depth_mapper_icp import IcpResult, IcpSettings, align
from depth_mapper_model import VoxelModel

F32 = npt.NDArray[np.float32]
FloatArray = npt.NDArray[np.float64]

OdometrySample = tuple[int, float, float, float]  # stamp (ns), x, y, yaw in odom


@dataclass(frozen=True)
class MapperSettings:
    """Everything the node takes as parameters.

    Attributes:
        voxel_size: model voxel edge (m).
        min_depth: nearer points are ignored (m).
        max_depth: farther points are ignored: the noise grows with depth squared (m).
        mount: the optical frame's origin in ``base_link`` (x, y, z).
        icp: the alignment's rules.
        icp_stride: ICP uses every ``icp_stride``-th pixel in each direction.
        icp_max_points: and at most this many of them.
        normal_step: pixel baseline of the normals.
        keyframe_distance: a new keyframe after this much travel (m)...
        keyframe_angle: ...or this much turn (rad).
        odom_sigma_fixed: prior standard deviation of the predicted position per frame (m)...
        odom_sigma_per_metre: ...plus this much per metre moved.
        odom_sigma_yaw_fixed: prior standard deviation of the predicted yaw per frame (rad)...
        odom_sigma_yaw_per_radian: ...plus this much per radian turned.
        odom_wait_ns: a frame waits at most this long (stamp time) for odometry at its stamp.
        depth_noise: the camera's depth noise ``a + b (z - 0.4)^2`` (m), ``(a, b)``.
        backend: keyframe linking and loop closing.
        close_loops: look for loop closures (else keyframes only feed the model).
        relocalise_distance: when tracking fails, pairs this far apart are tried (m)...
        relocalise_min_pairs: ...and a result with this many pairs is taken.
        calibrate_odometry: learn the odometry's heading error while tracking.
        calibration_yaw_sigma: only frames whose geometry gives the yaw this well (rad)
            teach the calibration.
        calibration_ridge: how much evidence (squared increments) the calibration needs
            before it departs from zero.
    """

    voxel_size: float = 0.05
    min_depth: float = 0.3
    max_depth: float = 5.0
    mount: tuple[float, float, float] = (0.12, 0.0, 0.25)
    icp: IcpSettings = field(default_factory=IcpSettings)
    icp_stride: int = 2
    icp_max_points: int = 600
    normal_step: int = 2
    keyframe_distance: float = 0.25
    keyframe_angle: float = math.radians(12.0)
    odom_sigma_fixed: float = 0.002
    odom_sigma_per_metre: float = 0.03
    odom_sigma_yaw_fixed: float = 0.003
    odom_sigma_yaw_per_radian: float = 0.1
    odom_wait_ns: int = 500_000_000
    depth_noise: tuple[float, float] = (0.0012, 0.0019)
    backend: BackendSettings = field(default_factory=BackendSettings)
    close_loops: bool = True
    relocalise_distance: float = 0.5
    relocalise_min_pairs: int = 150
    calibrate_odometry: bool = True
    calibration_yaw_sigma: float = 0.003
    calibration_ridge: float = 0.05


@dataclass(frozen=True)
class FrameResult:
    """What one depth frame did.

    Attributes:
        stamp_ns: the frame's stamp.
        pose: ``base_link`` in ``map`` after the frame.
        tracked: the ICP found enough pairs (else the pose is the odometry prediction).
        pairs: ICP pairs accepted.
        keyframe: the frame became a keyframe and was fused into the model.
        valid_points: pixels with a usable depth.
        rms: point-to-plane residual (m).
        first: the model was empty before this frame (nothing to track against yet).
        loop: what the keyframe's loop search came to (NONE for other frames).
    """

    stamp_ns: int
    pose: FloatArray
    tracked: bool
    pairs: int
    keyframe: bool
    valid_points: int
    rms: float
    first: bool
    loop: LoopClosure = LoopClosure.NONE


class DepthMapper:
    """Tracks the camera against a voxel model it builds.

    Args:
        settings: parameters.
        start: the robot's start pose ``[x, y, yaw]`` in ``map``.

    Attributes (the state):
        model: the voxel model.
        pose: ``base_link`` in ``map`` at the last frame.
        last_frame_ns: the last frame's stamp (-1 before the first).
        odom_at_pose: the odometry pose at the last frame (at first the odom origin, which is
            the start pose; None if a frame came without any odometry).
        odometry: recent odometry samples ``(stamp_ns, x, y, yaw)``, oldest first.
        pending: frames waiting for odometry at their stamp ``(stamp_ns, points)``.
        backend: the keyframes (with their clouds) and the pose graph.
        calibration: the odometry's learnt heading error.
        yaw_observed: the last frame's yaw was pinned down by the geometry.
        counters: frames, tracked, keyframes and rejected inputs so far.
    """

    def __init__(self, settings: MapperSettings, start: FloatArray) -> None:
        self.settings = settings
        self.model = VoxelModel(settings.voxel_size)
        self.pose: FloatArray = np.asarray(start, dtype=np.float64).copy()
        self.last_frame_ns = -1
        # The start pose is the odom frame's origin (map -> odom is the start pose), so the
        # first frame is placed by the odometry it has moved since.
        self.odom_at_pose: tuple[float, float, float] | None = (0.0, 0.0, 0.0)
        self.odometry: deque[OdometrySample] = deque(maxlen=200)
        self.pending: deque[tuple[int, F32]] = deque(maxlen=10)
        self.backend = Backend(settings.backend, settings.voxel_size)
        self.calibration = HeadingCalibration(settings.calibration_ridge)
        self.yaw_observed = False
        self.counters: dict[str, int] = dict.fromkeys(
            ('frames', 'tracked', 'keyframes', 'loops', 'graph_solves', 'relocalised',
             'extrapolated', 'empty_frames', 'stale_frames', 'stale_odometry'), 0)

    # -- inputs ----------------------------------------------------------------------------------

    def add_odometry(self, stamp_ns: int, x: float, y: float, yaw: float) -> list[FrameResult]:
        """One odometry sample (``base_link`` in ``odom``); frames it was awaited for, processed.

        Samples that are not newer than the last one are ignored (and counted).
        """
        if self.odometry and stamp_ns <= self.odometry[-1][0]:
            self.counters['stale_odometry'] += 1
            return []
        self.odometry.append((stamp_ns, float(x), float(y), float(yaw)))
        results = []
        while self.pending and self.pending[0][0] <= stamp_ns:
            frame_ns, points = self.pending.popleft()
            results.append(self._process(frame_ns, points))
        return results

    def add_frame(self, stamp_ns: int, points: F32) -> list[FrameResult]:
        """One organised depth frame ``(h, w, 3)`` in the optical frame.

        It is processed as soon as odometry at its stamp is in (at once, usually), else it
        waits in ``pending``; a frame that waited ``odom_wait_ns`` for it is processed with
        the odometry extrapolated at its last velocity. Without any odometry at all, frames
        are tracked from the model alone, one frame late. Frames not newer than the last one
        are ignored.

        Returns:
            the frames processed by this call, oldest first.
        """
        newest = self.pending[-1][0] if self.pending else self.last_frame_ns
        if stamp_ns <= newest:
            self.counters['stale_frames'] += 1
            return []
        results = []
        while self.pending and stamp_ns - self.pending[0][0] >= self.settings.odom_wait_ns:
            frame_ns, old = self.pending.popleft()
            results.append(self._process(frame_ns, old))
        if self.pending or not self.odometry or self.odometry[-1][0] < stamp_ns:
            self.pending.append((stamp_ns, points))
            if not self.odometry and len(self.pending) > 1:
                # No odometry at all (yet): do not hold frames back; track from the model.
                frame_ns, old = self.pending.popleft()
                results.append(self._process(frame_ns, old))
        else:
            results.append(self._process(stamp_ns, points))
        return results

    # -- one frame ------------------------------------------------------------------------------

    def _odometry_at(self, stamp_ns: int) -> tuple[float, float, float] | None:
        """The odometry pose at a stamp: interpolated, or extrapolated at the last velocity
        (at most ``odom_wait_ns`` ahead) for a frame that could not wait any longer."""
        if not self.odometry:
            return None
        newest = self.odometry[-1]
        if stamp_ns >= newest[0]:
            if stamp_ns == newest[0] or len(self.odometry) < 2:
                return newest[1:]
            self.counters['extrapolated'] += 1
            before = self.odometry[-2]
            ahead = min(stamp_ns - newest[0], self.settings.odom_wait_ns)
            p = interpolate(np.array(before[1:]), np.array(newest[1:]),
                            1.0 + ahead / (newest[0] - before[0]))
            return float(p[0]), float(p[1]), float(p[2])
        previous = self.odometry[0]
        if stamp_ns <= previous[0]:
            return previous[1:]
        for sample in self.odometry:
            if sample[0] == stamp_ns:
                # As it is, the same pose as when it was the newest: through interpolate()
                # (fraction 1, wrapped yaw) its last bits would change, and the frame's result
                # would depend on whether later odometry had arrived before it.
                return sample[1:]
            if sample[0] >= stamp_ns:
                fraction = (stamp_ns - previous[0]) / (sample[0] - previous[0])
                p = interpolate(np.array(previous[1:]), np.array(sample[1:]), fraction)
                return float(p[0]), float(p[1]), float(p[2])
            previous = sample
        return newest[1:]

    def _odometry_motion(self, start: tuple[float, float, float],
                         end: tuple[float, float, float]) -> tuple[FloatArray, FloatArray]:
        """The odometry's motion from ``start`` to ``end`` (corrected) and its information."""
        s = self.settings
        delta = between(np.array(start), np.array(end))
        if s.calibrate_odometry:
            delta[2] = self.calibration.corrected_yaw(float(delta[2]), float(delta[0]))
        moved = math.hypot(delta[0], delta[1])
        sigma_xy = s.odom_sigma_fixed + s.odom_sigma_per_metre * moved
        sigma_yaw = s.odom_sigma_yaw_fixed + s.odom_sigma_yaw_per_radian * abs(delta[2]) + (
            0.5 * s.odom_sigma_per_metre * moved)
        information = np.diag([1.0 / sigma_xy**2, 1.0 / sigma_xy**2, 1.0 / sigma_yaw**2])
        return delta, information

    def _predict(self, odom: tuple[float, float, float] | None) -> tuple[FloatArray, FloatArray]:
        """The predicted pose and the information (inverse covariance) of the prediction."""
        if odom is None or self.odom_at_pose is None:
            # No motion prior: a weak one that keeps the pose where it was.
            return self.pose.copy(), np.diag([1.0 / 0.1**2, 1.0 / 0.1**2, 1.0 / 0.1**2])
        delta, information = self._odometry_motion(self.odom_at_pose, odom)
        return compose(self.pose, delta), information

    def _process(self, stamp_ns: int, points: F32) -> FrameResult:
        s = self.settings
        odom = self._odometry_at(stamp_ns)
        prior, information = self._predict(odom)
        valid = valid_mask(points, s.min_depth, s.max_depth)
        n_valid = int(valid.sum())
        self.counters['frames'] += 1
        tracked = False
        yaw_observed = False
        pairs = 0
        rms = 0.0
        keyframe = False
        loop = LoopClosure.NONE
        pose = prior
        first = len(self.model) == 0
        if n_valid < s.icp.min_pairs:
            self.counters['empty_frames'] += 1
        else:
            normals_o, has_normal = organised_normals(points, valid, s.normal_step)
            base = optical_to_base(points, s.mount)
            normals = optical_directions_to_base(normals_o)
            depth = np.where(valid, points[..., 2], 0.0).astype(np.float64)
            sigma = s.depth_noise[0] + s.depth_noise[1] * (np.maximum(depth, 0.4) - 0.4) ** 2
            if len(self.model):
                sel = self._icp_selection(valid & has_normal, normals)
                result = align(self.model, base[sel], normals[sel], sigma[sel], prior,
                               information, s.icp)
                if not result.tracked:
                    result = self._relocalise(base[sel], normals[sel], sigma[sel], prior,
                                              information, result)
                pose, tracked, pairs, rms = result.pose, result.tracked, result.pairs, result.rms
                yaw_observed = result.yaw_sigma < s.calibration_yaw_sigma
            if self._is_keyframe(pose):
                keyframe = True
                weights = 1.0 / sigma[valid] ** 2
                normal_sums = np.where(has_normal[valid][:, None], normals[valid], 0.0)
                cloud = downsample(base[valid], normal_sums * weights[:, None], weights,
                                   s.voxel_size)
                pose, loop = self._add_keyframe(Keyframe(stamp_ns, np.asarray(pose).copy(),
                                                         odom, *cloud))
        if tracked:
            self.counters['tracked'] += 1
        # A loop closure that moved the keyframes moved this pose too: the turn since the last
        # frame then holds the loop's correction, which is not the odometry's error.
        if yaw_observed and self.yaw_observed and odom is not None and (
                self.odom_at_pose is not None) and loop is not LoopClosure.MOVED:
            delta = between(np.array(self.odom_at_pose), np.array(odom))
            self.calibration.observe(float(delta[2]), float(delta[0]),
                                     wrap(float(pose[2]) - float(self.pose[2])))
        self.yaw_observed = yaw_observed
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self.pose[2] = wrap(float(self.pose[2]))
        self.last_frame_ns = stamp_ns
        if odom is not None:
            self.odom_at_pose = (float(odom[0]), float(odom[1]), float(odom[2]))
        return FrameResult(stamp_ns, self.pose.copy(), tracked, pairs, keyframe, n_valid, rms,
                           first, loop)

    def _relocalise(self, points: FloatArray, normals: FloatArray, sigma: FloatArray,
                    prior: FloatArray, information: FloatArray, failed: IcpResult) -> IcpResult:
        """Tracking failed: search wider around the prediction (a glitch in the odometry, a
        frame lost), coarse to fine, and keep the result only if it fits well."""
        s = self.settings
        wide = dataclasses.replace(s.icp, max_distance=s.relocalise_distance, iterations=15)
        weak = information * 0.01
        coarse = align(self.model, points, normals, sigma, prior, weak, wide)
        if not coarse.tracked:
            return failed
        fine = align(self.model, points, normals, sigma, coarse.pose, weak, s.icp)
        if fine.tracked and fine.pairs >= s.relocalise_min_pairs and fine.rms <= s.icp.huber:
            self.counters['relocalised'] += 1
            return fine
        return failed

    def _icp_selection(self, usable: npt.NDArray[np.bool_], normals: FloatArray
                       ) -> npt.NDArray[np.bool_]:
        """Pixels for the ICP: on a grid, with a normal that is not vertical (the floor says
        nothing about a planar pose), at most ``icp_max_points``, spread evenly."""
        s = self.settings
        grid = np.zeros_like(usable)
        grid[::s.icp_stride, ::s.icp_stride] = True
        horizontal = np.hypot(normals[..., 0], normals[..., 1]) > 0.3
        chosen = usable & grid & horizontal
        flat = np.flatnonzero(chosen)
        if flat.size > s.icp_max_points:
            keep = flat[np.linspace(0, flat.size - 1, s.icp_max_points).astype(np.int64)]
            chosen = np.zeros_like(usable)
            chosen.flat[keep] = True
        return chosen

    def _add_keyframe(self, kf: Keyframe) -> tuple[FloatArray, LoopClosure]:
        """Link the keyframe into the graph, fuse it, close a loop; its (new) pose."""
        backend = self.backend
        previous = backend.keyframes[-1] if backend.keyframes else None
        if previous is not None and previous.odom is not None and kf.odom is not None:
            delta, information = self._odometry_motion(previous.odom, kf.odom)
            backend.add(kf, delta, information)
        else:
            backend.add(kf, None, None)
        integrate_keyframe(self.model, kf)
        self.counters['keyframes'] += 1
        outcome = backend.close_loop() if self.settings.close_loops else LoopClosure.NONE
        if outcome is not LoopClosure.NONE:
            self.counters['loops'] += 1
        if outcome is LoopClosure.MOVED:
            backend.rebuild(self.model)
            self.counters['graph_solves'] += 1
        return kf.pose.copy(), outcome

    def _is_keyframe(self, pose: FloatArray) -> bool:
        if not self.backend.keyframes:
            return True
        x, y, yaw = (float(v) for v in self.backend.keyframes[-1].pose)
        return (math.hypot(pose[0] - x, pose[1] - y) >= self.settings.keyframe_distance
                or abs(wrap(float(pose[2]) - yaw)) >= self.settings.keyframe_angle)
