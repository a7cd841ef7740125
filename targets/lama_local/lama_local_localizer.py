"""LaMa-style localization without ROS: the map, odometry and scans in, a pose out.

Predict with the odometry's motion since the last update, then refine the prediction by
matching the scan to the map (``lama_local_matcher``). The match runs only once the odometry
says the robot moved ``update_min_d`` or turned ``update_min_a`` since the last one (and on the
first scan after an initial pose); in between, the pose given out is the last match carried
forward by the odometry. A scan that cannot be matched (too few points near obstacles) leaves
the prediction, and the covariance grows with the motion.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from lama_local_matcher import DistanceMap, MatcherConfig, match
from lama_local_scan import scan_points
from planar_geometry import OdometrySample, Pose, compose, odometry_at, relative
from planar_map import GridMap

FloatArray = npt.NDArray[np.float64]

TIME_JUMP_NS = 1_000_000_000  # odometry this far back in time: the clock was reset

# Growth of the covariance over a motion that could not be matched (per metre and radian).
UNMATCHED_TRANSLATION_NOISE = 0.2
UNMATCHED_ROTATION_NOISE = 0.2


class ScanSkipped(Exception):
    """A scan the localizer could not use; the message says why."""


@dataclass(frozen=True)
class LamaConfig:
    """Everything the node's parameters set.

    Attributes:
        matcher: Gauss-Newton settings.
        update_min_d: translation that triggers a match (m).
        update_min_a: rotation that triggers a match (rad).
        laser: the lidar's pose in base_link (x, y, yaw).
        max_beams: beams used per scan, evenly spaced (0: all).
        odometry_history: odometry samples kept to look up the pose at a scan's stamp.
    """

    matcher: MatcherConfig = field(default_factory=MatcherConfig)
    update_min_d: float = 0.05
    update_min_a: float = 0.05
    laser: Pose = (-0.064, 0.0, 0.0)
    max_beams: int = 0
    odometry_history: int = 100


@dataclass(frozen=True)
class PoseEstimate:
    """The localizer's answer for one scan.

    Attributes:
        stamp_ns: the scan's stamp.
        pose: (x, y, yaw) of base_link in map.
        covariance: 3 x 3 (x, y, yaw).
        updated: whether a match was attempted on this scan.
        matched: whether it succeeded.
        points: scan points the match used.
    """

    stamp_ns: int
    pose: Pose
    covariance: FloatArray
    updated: bool
    matched: bool
    points: int


class LamaLocalizer:
    """Scan-matching localization on a known map.

    Attributes:
        pose: base_link in map at the last update.
        covariance: its 3 x 3 covariance.
        grid: the map (None until one arrives).
        odometry: recent odometry samples ``(stamp_ns, x, y, yaw)``.
        odom_at_update: the odometry pose at the last update (None before the first).
        force_update: match on the next scan even without motion.
    """

    def __init__(self, config: LamaConfig, initial_pose: Pose,
                 initial_covariance: FloatArray) -> None:
        self.config = config
        self.pose: Pose = (float(initial_pose[0]), float(initial_pose[1]), float(initial_pose[2]))
        self.covariance: FloatArray = np.array(initial_covariance, dtype=np.float64)
        self.grid: GridMap | None = None
        self.odometry: deque[OdometrySample] = deque(maxlen=config.odometry_history)
        self.odom_at_update: Pose | None = None
        self.force_update = True
        # Cache derived from the map (rebuilt when the map object changes, e.g. after a
        # restored checkpoint replaced it).
        self._distance: DistanceMap | None = None

    # -- inputs ---------------------------------------------------------------------------------

    def set_map(self, grid: GridMap) -> None:
        """Take a new map."""
        self.grid = grid
        self._distance_map()

    def add_odometry(self, stamp_ns: int, pose: Pose) -> bool:
        """One odometry pose (odom frame) at its stamp.

        Returns:
            False when the sample was older than the newest one and ignored. A stamp more than
            ``TIME_JUMP_NS`` back is a clock reset (a restarted simulation or bag): the history
            starts over from it.
        """
        stamp_ns = int(stamp_ns)
        if self.odometry and stamp_ns < self.odometry[-1][0]:
            if self.odometry[-1][0] - stamp_ns <= TIME_JUMP_NS:
                return False
            self.odometry.clear()
        self.odometry.append((stamp_ns, float(pose[0]), float(pose[1]), float(pose[2])))
        return True

    def set_pose(self, pose: Pose, covariance: FloatArray) -> None:
        """Restart from ``pose`` (an initial pose); the next scan is matched."""
        self.pose = (float(pose[0]), float(pose[1]), float(pose[2]))
        self.covariance = np.array(covariance, dtype=np.float64)
        self.odom_at_update = self.odometry[-1][1:] if self.odometry else None
        self.force_update = True

    def process_scan(self, stamp_ns: int, ranges: npt.ArrayLike, angle_min: float,
                     angle_increment: float, range_min: float, range_max: float) -> PoseEstimate:
        """Match the scan if the robot moved enough; the pose at the scan's stamp.

        Raises:
            ScanSkipped: no map or no odometry yet, or the scan's geometry is unusable.
        """
        distance = self._distance_map()
        odom = odometry_at(self.odometry, stamp_ns)
        if odom is None:
            raise ScanSkipped('no odometry yet')
        try:
            px, py = scan_points(ranges, angle_min, angle_increment, range_min, range_max,
                                 self.config.laser, self.config.max_beams)
        except ValueError as err:
            raise ScanSkipped(f'unusable scan: {err}') from err
        if self.odom_at_update is None:
            self.odom_at_update = odom
            self.force_update = True
        motion = relative(self.odom_at_update, odom)
        moved = (math.hypot(motion[0], motion[1]) >= self.config.update_min_d
                 or abs(motion[2]) >= self.config.update_min_a)
        ran = moved or self.force_update
        matched, points = False, 0
        if ran:
            predicted = compose(self.pose, motion)
            result = match(distance, px, py, predicted, self.config.matcher)
            if result.ok and result.covariance is not None:
                self.pose, self.covariance = result.pose, result.covariance
                matched, points = True, result.points
            else:
                self.pose = predicted
                self.covariance = self.covariance + self._unmatched_noise(motion)
            self.odom_at_update = odom
            self.force_update = False
        pose = compose(self.pose, relative(self.odom_at_update, odom))
        return PoseEstimate(int(stamp_ns), pose, self.covariance.copy(), ran, matched, points)

    @staticmethod
    def _unmatched_noise(motion: Pose) -> FloatArray:
        trans = math.hypot(motion[0], motion[1])
        sd_xy = UNMATCHED_TRANSLATION_NOISE * trans
        sd_yaw = UNMATCHED_ROTATION_NOISE * abs(motion[2]) + 0.5 * UNMATCHED_ROTATION_NOISE * trans
        return np.diag([sd_xy ** 2, sd_xy ** 2, sd_yaw ** 2])

    # -- cache ----------------------------------------------------------------------------------

    def _distance_map(self) -> DistanceMap:
        if self.grid is None:
            raise ScanSkipped('no map yet')
        if self._distance is None or self._distance.grid is not self.grid:
            self._distance = DistanceMap(self.grid, self.config.matcher.max_distance)
        return self._distance
