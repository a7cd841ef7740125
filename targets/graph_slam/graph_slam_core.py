"""Graph SLAM without ROS: odometry and scans in, keyframe graph, pose and map out.

``GraphSlam`` is everything the node knows. Its key state is plain data (see keyvars.yaml):
the keyframes (poses and scans), the edges with their information matrices, the current pose,
the odometry received (a short history to look up the pose at a scan's stamp) and the grid.
The likelihood field of the recent keyframes is a cache, rebuilt from them when missing.

Per scan (``add_scan``):

1. the pose at the scan's stamp is predicted from the odometry since the previous scan,
   interpolated at the stamp (a scan that arrives ahead of its odometry waits for it);
2. the scan is matched (Gauss-Newton on a likelihood field) against the last few keyframes,
   which corrects the prediction (the front end);
3. once the robot has moved ``keyframe_distance`` or turned ``keyframe_angle`` since the last
   keyframe, the scan becomes a keyframe, linked to the previous one by the matched relative
   pose; its scan is added to the grid;
4. loop closure: earlier keyframes near the new one in the current estimate, but reached by a
   long way round (``loop_min_travel``), are candidates; each is verified by a correlative
   search and refinement against that keyframe and its neighbours, with a fitness check (the
   fraction of points that land on the reference) and a degeneracy check (a corridor pins
   nothing down along it) before it becomes an edge;
5. with a new loop edge the graph is optimised (Gauss-Newton), unless the estimate already
   agrees with it; a loop closure that leaves an edge badly violated afterwards is withdrawn;
   when keyframes moved, the grid is rebuilt from every keyframe at its optimised pose.
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from graph_slam_graph import (
    Edge,
    EdgeKind,
    Keyframe,
    OptimisationResult,
    chi2,
    edge_errors,
    information,
    optimise,
)
from graph_slam_grid import OccupancyCounts, rebuild, scan_in_map
from graph_slam_matcher import (
    Reference,
    build_field,
    build_reference,
    estimate_normals,
    icp,
    search,
)
from graph_slam_scan import PointArray, thin_points, thin_points_index
from graph_slam_se2 import FloatArray, between, compose, pose, transform_points, wrap_angle

OdometrySample = tuple[int, float, float, float]  # (stamp ns, x, y, yaw) in the odom frame


@dataclass(frozen=True)
class GraphSlamConfig:
    """Parameters (ROS parameters of the node; never state).

    Attributes:
        map_start: the robot's start pose in the map frame (where ``odom`` is).
        laser_pose: the laser frame in the base frame ``(x, y, yaw)``.
        resolution: grid cell side (m).
        keyframe_distance: a new keyframe after this much travel (m)...
        keyframe_angle: ...or this much turning (rad).
        scan_matching: refine odometry by scan matching (off: odometry-only mapping).
        loop_closure: look for loop closures.
        local_keyframes: how many recent keyframes the scan is matched against.
        match_resolution: cell of the ICP reference's nearest-point grid (m).
        match_reach: ICP correspondences are at most this far apart (m).
        reference_spacing: reference points closer than this are merged (m).
        match_point_spacing: scan points are thinned to about this spacing for matching (m).
        track_min_inliers: a tracking match with fewer inliers than this fraction is not
            trusted (the odometry prediction is used).
        track_max_correction: nor one moving the prediction more than this (m).
        loop_closure_radius: candidates lie within this distance of the new keyframe (m).
        loop_min_travel: ...and were left at least this far back along the path (m).
        loop_max_candidates: at most this many candidates verified per keyframe.
        loop_submap_keyframes: the candidate's neighbours on each side matched with it.
        loop_search_window: correlative search ± this around the estimate (m).
        loop_search_angle: ... and ± this (rad).
        loop_search_resolution: the search's grid cell and likelihood field sigma (m).
        loop_search_angle_step: the search's rotation step (rad).
        loop_min_fitness: fraction of points within ``loop_inlier_distance`` of the reference.
        loop_inlier_distance: (m).
        loop_min_constraint: smallest translational eigenvalue of the match Hessian per point
            (1/m²); below it the match slides (a corridor) and is refused.
        loop_max_residual: after optimisation, an edge off by more than this (m) withdraws the
            new loop closure.
        loop_settled_chi2: new loop edges whose chi² at the current estimate is below this
            (within about a standard deviation) are added without optimising.
        sigma_match_xy: standard deviation of a matched edge, translation (m).
        sigma_match_yaw: ... rotation (rad).
        sigma_loop_xy: of a loop edge (m).
        sigma_loop_yaw: (rad).
        sigma_odom_xy: of an odometry-only edge, per metre driven, plus a floor (m).
        sigma_odom_yaw: ... per radian turned (rad).
        optimise_iterations: Gauss-Newton iterations at most.
        rebuild_threshold: rebuild the grid when a keyframe moved more than this (m) or turned
            more than this over 2 m (rad * 2 m) in an optimisation.
        odometry_max_gap: a scan further than this from any odometry is skipped (s).
        max_waiting_scans: at most this many scans wait for odometry up to their stamp.
        hit_depth: a return is counted this far behind the measured range (m).
        hit_log_odds / pass_log_odds: the inverse sensor model.
        occupied_above / free_below: probabilities that make a cell occupied / free.
    """

    map_start: tuple[float, float, float] = (0.0, 0.0, 0.0)
    laser_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    resolution: float = 0.05
    keyframe_distance: float = 0.3
    keyframe_angle: float = 0.3
    scan_matching: bool = True
    loop_closure: bool = True
    local_keyframes: int = 10
    match_resolution: float = 0.05
    match_reach: float = 0.3
    reference_spacing: float = 0.025
    match_point_spacing: float = 0.025
    track_min_inliers: float = 0.3
    track_max_correction: float = 0.25
    loop_closure_radius: float = 2.0
    loop_min_travel: float = 4.0
    loop_max_candidates: int = 2
    loop_submap_keyframes: int = 3
    loop_search_window: float = 0.5
    loop_search_angle: float = 0.3
    loop_search_resolution: float = 0.1
    loop_search_angle_step: float = 0.02
    loop_min_fitness: float = 0.6
    loop_inlier_distance: float = 0.1
    loop_min_constraint: float = 0.05
    loop_max_residual: float = 0.15
    loop_settled_chi2: float = 1.0
    sigma_match_xy: float = 0.02
    sigma_match_yaw: float = 0.01
    sigma_loop_xy: float = 0.03
    sigma_loop_yaw: float = 0.015
    sigma_odom_xy: float = 0.1
    sigma_odom_yaw: float = 0.1
    optimise_iterations: int = 10
    rebuild_threshold: float = 0.02
    odometry_max_gap: float = 0.25
    max_waiting_scans: int = 50
    hit_depth: float = 0.02
    hit_log_odds: float = 0.6
    pass_log_odds: float = -0.4
    occupied_above: float = 0.65
    free_below: float = 0.25


@dataclass
class LoopClosure:
    """A verified loop closure (reported, never state: the edge itself is)."""

    source: int
    target: int
    fitness: float
    constraint: float
    correction: float  # how far the match moved the estimate (m)


@dataclass
class ScanOutcome:
    """What one scan did (for the node's output and logs; never state).

    Attributes:
        stamp_ns: the scan's stamp.
        pose: the robot's pose in map at the scan (None if skipped).
        skipped: why the scan was not used ('' if it was).
        matched: whether scan matching corrected the odometry's prediction.
        keyframe: the index of the keyframe it became, if it did.
    """

    stamp_ns: int
    pose: FloatArray | None = None
    skipped: str = ''
    matched: bool = False
    keyframe: int | None = None
    loop_closures: list[LoopClosure] = field(default_factory=list)
    rejected_loops: int = 0
    optimisation: OptimisationResult | None = None
    optimise_seconds: float = 0.0
    rebuild_seconds: float = 0.0
    grid_rebuilt: bool = False


class NoOdometryError(LookupError):
    """There is no odometry close enough to a scan's stamp (the message says how far)."""


class OutOfOrderError(ValueError):
    """A message not newer than the one before it on its topic."""


class GraphSlam:
    """Keyframe pose-graph SLAM on 2D scans and wheel odometry.

    Args:
        config: the parameters.
    """

    def __init__(self, config: GraphSlamConfig) -> None:
        self.config = config
        self.laser = np.array(config.laser_pose, dtype=np.float64)
        # -- key state --
        self.odom_history: deque[OdometrySample] = deque(maxlen=250)  # 5 s at 50 Hz
        self.last_scan_stamp_ns: int | None = None
        self.last_scan_odom: FloatArray | None = None  # odom pose at the previous scan
        self.waiting_scans: deque[tuple[int, PointArray]] = deque()  # ahead of the odometry
        self.pose: FloatArray | None = None  # current estimate in map
        self.unmatched_since_keyframe = False
        self.keyframes: list[Keyframe] = []
        self.edges: list[Edge] = []
        self.grid = OccupancyCounts.empty(config.resolution)
        # -- caches (rebuilt from the state above when None) --
        self._local_reference_cache: Reference | None = None

    # -- inputs -----------------------------------------------------------------------------

    def add_odometry(self, stamp_ns: int, x: float, y: float, yaw: float) -> list[ScanOutcome]:
        """One odometry pose (odom frame); the outcomes of the waiting scans it completes.

        Raises:
            OutOfOrderError: not newer than the last odometry (ignored).
        """
        if self.odom_history and stamp_ns <= self.odom_history[-1][0]:
            msg = 'not newer than the last odometry'
            raise OutOfOrderError(msg)
        self.odom_history.append((stamp_ns, x, y, yaw))
        return self._drain()

    def odometry_at(self, stamp_ns: int) -> FloatArray:
        """The odometry pose at ``stamp_ns``, interpolated between the samples around it.

        Raises:
            NoOdometryError: no sample within ``odometry_max_gap`` of the stamp.
        """
        history = self.odom_history
        if not history:
            msg = 'no odometry received yet'
            raise NoOdometryError(msg)
        gap = int(self.config.odometry_max_gap * 1e9)
        newest, oldest = history[-1], history[0]
        if stamp_ns >= newest[0] or stamp_ns <= oldest[0]:
            sample = newest if stamp_ns >= newest[0] else oldest
            if abs(stamp_ns - sample[0]) > gap:
                msg = (f'nearest odometry is {abs(stamp_ns - sample[0]) / 1e9:.3f} s from the '
                       'scan')
                raise NoOdometryError(msg)
            return pose(sample[1], sample[2], sample[3])
        k = len(history) - 1
        while history[k - 1][0] > stamp_ns:
            k -= 1
        a, b = history[k - 1], history[k]
        nearest = min(stamp_ns - a[0], b[0] - stamp_ns)
        if nearest > gap:  # a hole in the odometry: interpolating across it is a guess
            msg = f'nearest odometry is {nearest / 1e9:.3f} s from the scan'
            raise NoOdometryError(msg)
        f = (stamp_ns - a[0]) / (b[0] - a[0])
        return pose(a[1] + f * (b[1] - a[1]), a[2] + f * (b[2] - a[2]),
                    a[3] + f * wrap_angle(b[3] - a[3]))

    def add_scan(self, stamp_ns: int, points: PointArray) -> list[ScanOutcome]:
        """One scan (points in the base frame); the outcomes of the scans processed now.

        A scan newer than the newest odometry waits for odometry up to its stamp (messages of
        two topics arrive in no guaranteed order, least of all after a stall); this one, and
        any that waited, are processed as soon as that odometry is in. A scan waits at most
        ``max_waiting_scans`` scans long (then the oldest is dropped, reported as skipped).

        Raises:
            OutOfOrderError: not newer than the last scan (ignored).
        """
        newest = self.waiting_scans[-1][0] if self.waiting_scans else self.last_scan_stamp_ns
        if newest is not None and stamp_ns <= newest:
            msg = 'not newer than the last scan'
            raise OutOfOrderError(msg)
        self.waiting_scans.append((stamp_ns, points))
        outcomes = []
        if len(self.waiting_scans) > self.config.max_waiting_scans:
            dropped, _ = self.waiting_scans.popleft()
            outcomes.append(ScanOutcome(dropped, skipped=(
                f'no odometry up to its stamp ({dropped / 1e9:.2f} s) while '
                f'{self.config.max_waiting_scans} more scans came')))
        return outcomes + self._drain()

    def _drain(self) -> list[ScanOutcome]:
        """Process the waiting scans that odometry has caught up with, oldest first."""
        outcomes = []
        while (self.waiting_scans and self.odom_history
               and self.waiting_scans[0][0] <= self.odom_history[-1][0]):
            stamp_ns, points = self.waiting_scans.popleft()
            try:
                outcomes.append(self._process(stamp_ns, points, self.odometry_at(stamp_ns)))
            except NoOdometryError as err:
                outcomes.append(ScanOutcome(stamp_ns, skipped=str(err)))
        return outcomes

    def _process(self, stamp_ns: int, points: PointArray, odom: FloatArray) -> ScanOutcome:
        """Track one scan from the odometry at its stamp; add a keyframe and close loops."""
        cfg = self.config
        if self.pose is None or self.last_scan_odom is None:
            start = np.array(cfg.map_start, dtype=np.float64)
            self.pose = compose(start, odom)
            self.last_scan_odom = odom
            self.last_scan_stamp_ns = stamp_ns
            index = self._add_keyframe(stamp_ns, points, None)
            return ScanOutcome(stamp_ns, self.pose.copy(), keyframe=index)
        predicted = compose(self.pose, between(self.last_scan_odom, odom))
        self.last_scan_odom = odom
        self.last_scan_stamp_ns = stamp_ns
        matched = False
        if cfg.scan_matching and points.shape[0] >= 20:
            match = icp(self._local_reference(), thin_points(points, cfg.match_point_spacing),
                        predicted, inlier_distance=cfg.loop_inlier_distance)
            correction = math.hypot(float(match.pose[0] - predicted[0]),
                                    float(match.pose[1] - predicted[1]))
            if match.inliers >= cfg.track_min_inliers and correction <= cfg.track_max_correction:
                predicted, matched = match.pose, True
        self.pose = predicted
        if not matched:
            self.unmatched_since_keyframe = True
        outcome = ScanOutcome(stamp_ns, self.pose.copy(), matched=matched)
        last = self.keyframes[-1]
        step = between(last.pose, self.pose)
        if (math.hypot(float(step[0]), float(step[1])) >= cfg.keyframe_distance
                or abs(float(step[2])) >= cfg.keyframe_angle):
            outcome.keyframe = self._add_keyframe(stamp_ns, points, step)
            if cfg.loop_closure:
                self._close_loops(outcome)
            outcome.pose = self.pose.copy()
        return outcome

    # -- keyframes and the local map --------------------------------------------------------

    def _add_keyframe(self, stamp_ns: int, points: PointArray, step: FloatArray | None) -> int:
        assert self.pose is not None
        cfg = self.config
        travelled = 0.0
        if self.keyframes:
            previous = self.keyframes[-1]
            travelled = previous.travelled + math.hypot(float(self.pose[0] - previous.pose[0]),
                                                        float(self.pose[1] - previous.pose[1]))
        self.keyframes.append(Keyframe(stamp_ns, self.pose.copy(), points.copy(), travelled))
        index = len(self.keyframes) - 1
        if step is not None:
            if self.unmatched_since_keyframe or not cfg.scan_matching:
                dist, turn = math.hypot(float(step[0]), float(step[1])), abs(float(step[2]))
                info = information(0.02 + cfg.sigma_odom_xy * dist,
                                   0.01 + cfg.sigma_odom_yaw * turn + 0.02 * dist)
                kind = EdgeKind.ODOMETRY
            else:
                info = information(cfg.sigma_match_xy, cfg.sigma_match_yaw)
                kind = EdgeKind.SCAN_MATCH
            self.edges.append(Edge(index - 1, index, step, info, kind))
        self.unmatched_since_keyframe = False
        self.grid.add_scans([scan_in_map(self.pose, self.laser[:2], points)], cfg.hit_depth)
        self._local_reference_cache = None
        return index

    def _local_reference(self) -> Reference:
        """The last ``local_keyframes`` keyframes as an ICP reference (cached)."""
        if self._local_reference_cache is None:
            recent = self.keyframes[-self.config.local_keyframes:]
            self._local_reference_cache = self._reference(recent)
        return self._local_reference_cache

    def _reference(self, keyframes: list[Keyframe]) -> Reference:
        """Keyframes' points with their normals in the map, newest first, near-duplicates (the
        same wall seen again) dropped."""
        cfg = self.config
        points, normals, flags = [], [], []
        for k in reversed(keyframes):
            nrm, valid = estimate_normals(k.points)
            points.append(transform_points(k.pose, k.points))
            c, s = math.cos(k.pose[2]), math.sin(k.pose[2])
            normals.append(nrm @ np.array([[c, s], [-s, c]]))  # rotated into the map
            flags.append(valid)
        pts = np.concatenate(points)
        keep = thin_points_index(pts, cfg.reference_spacing)
        return build_reference(pts[keep], np.concatenate(normals)[keep],
                               np.concatenate(flags)[keep], cfg.match_resolution,
                               cfg.match_reach)

    # -- loop closure -----------------------------------------------------------------------

    def loop_candidates(self, index: int) -> list[int]:
        """Earlier keyframes near keyframe ``index`` that were left long ago, nearest first."""
        cfg = self.config
        new = self.keyframes[index]
        older = self.keyframes[:index]
        if not older:
            return []
        xy = np.array([k.pose[:2] for k in older])
        travelled = np.array([k.travelled for k in older])
        dist = np.hypot(xy[:, 0] - new.pose[0], xy[:, 1] - new.pose[1])
        ok = (dist <= cfg.loop_closure_radius) & (new.travelled - travelled >= cfg.loop_min_travel)
        candidates = np.flatnonzero(ok)
        picked: list[int] = []
        # nearest first, one per stretch of path (neighbours would repeat the same match)
        for j in candidates[np.argsort(dist[candidates], kind='stable')]:
            if all(abs(older[int(j)].travelled - older[p].travelled) > 1.0 for p in picked):
                picked.append(int(j))
            if len(picked) >= cfg.loop_max_candidates:
                break
        return picked

    def verify_loop(self, index: int, candidate: int) -> tuple[Edge, LoopClosure] | None:
        """Match keyframe ``index`` against ``candidate`` and its neighbours; an edge if the
        match is found, fits and is well constrained."""
        cfg = self.config
        new = self.keyframes[index]
        lo = max(0, candidate - cfg.loop_submap_keyframes)
        hi = candidate + cfg.loop_submap_keyframes + 1
        submap = [k for k in self.keyframes[lo:hi]
                  if new.travelled - k.travelled >= cfg.loop_min_travel]
        points = thin_points(new.points, cfg.match_point_spacing)
        if points.shape[0] < 20 or not submap:
            return None
        reference = self._reference(submap)
        coarse = build_field(reference.points, cfg.loop_search_resolution,
                             cfg.loop_search_resolution)
        sparse = points[::max(1, points.shape[0] // 80)]
        found, _ = search(coarse, sparse, new.pose, cfg.loop_search_window,
                          cfg.loop_search_angle, cfg.loop_search_angle_step)
        match = icp(reference, points, found, inlier_distance=cfg.loop_inlier_distance)
        fitness = match.inliers
        constraint = match.weakest_translation
        correction = math.hypot(float(match.pose[0] - new.pose[0]),
                                float(match.pose[1] - new.pose[1]))
        if (fitness < cfg.loop_min_fitness or constraint < cfg.loop_min_constraint
                or correction > cfg.loop_search_window * 1.5):
            return None
        source = self.keyframes[candidate]
        edge = Edge(candidate, index, between(source.pose, match.pose),
                    information(cfg.sigma_loop_xy, cfg.sigma_loop_yaw), EdgeKind.LOOP,
                    fitness)
        return edge, LoopClosure(candidate, index, fitness, constraint, correction)

    def _close_loops(self, outcome: ScanOutcome) -> None:
        assert outcome.keyframe is not None
        index = outcome.keyframe
        found: list[tuple[Edge, LoopClosure]] = []
        for candidate in self.loop_candidates(index):
            verified = self.verify_loop(index, candidate)
            if verified is not None:
                found.append(verified)
        if not found:
            return
        before = np.array([k.pose for k in self.keyframes])
        edges = self.edges + [edge for edge, _ in found]
        if float(chi2(before, [edge for edge, _ in found]).max()) < self.config.loop_settled_chi2:
            # The graph already agrees with the new edges: optimising would move nothing.
            self.edges = edges
            outcome.loop_closures = [closure for _, closure in found]
            return
        started = time.perf_counter()
        try:
            after, result = optimise(before, edges, self.config.optimise_iterations)
        except np.linalg.LinAlgError:  # a singular system: keep the graph as it was
            outcome.rejected_loops = len(found)
            return
        outcome.optimise_seconds = time.perf_counter() - started
        outcome.optimisation = result
        residual = edge_errors(after, edges)
        if float(np.hypot(residual[:, 0], residual[:, 1]).max()) > self.config.loop_max_residual:
            outcome.rejected_loops = len(found)
            return
        self.edges = edges
        outcome.loop_closures = [closure for _, closure in found]
        self._apply(after, result, outcome)

    def _apply(self, poses: FloatArray, result: OptimisationResult,
               outcome: ScanOutcome) -> None:
        """Move keyframes (and the current pose with the last one) to optimised poses."""
        assert self.pose is not None
        last = self.keyframes[-1]
        relative = between(last.pose, self.pose)
        for keyframe, new_pose in zip(self.keyframes, poses, strict=True):
            keyframe.pose = np.array(new_pose, dtype=np.float64)
        self.pose = compose(last.pose, relative)
        self._local_reference_cache = None
        if max(result.max_pose_change, 2.0 * result.max_yaw_change) > self.config.rebuild_threshold:
            started = time.perf_counter()
            self.grid = rebuild(self.config.resolution,
                                ((k.pose, k.points) for k in self.keyframes), self.laser[:2],
                                self.config.hit_depth)
            outcome.rebuild_seconds = time.perf_counter() - started
            outcome.grid_rebuilt = True

    # -- outputs ----------------------------------------------------------------------------

    def occupancy(self) -> npt.NDArray[np.int8]:
        """The map's cells (100 occupied, 0 free, -1 unknown), row 0 at the grid's origin."""
        cfg = self.config
        return self.grid.occupancy(cfg.hit_log_odds, cfg.pass_log_odds, cfg.occupied_above,
                                   cfg.free_below)

    def loop_closure_count(self) -> int:
        """Loop-closure edges in the graph."""
        return sum(1 for e in self.edges if e.kind is EdgeKind.LOOP)
