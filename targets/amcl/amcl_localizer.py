"""AMCL without ROS: the map, odometry and scans in, a pose with covariance out.

The node converts messages and calls these methods from its subscription callbacks; every
state change happens here, from message contents and stamps only. The filter runs on a scan
only once the odometry says the robot moved ``update_min_d`` or turned ``update_min_a`` since
the last filter update (and on the first scan after an initial pose); in between, the pose
given out is the last filter estimate carried forward by the odometry since (what
``map -> odom -> base_link`` gives a ROS navigator).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from amcl_filter import FilterConfig, ParticleFilter
from amcl_motion_model import MotionNoise
from amcl_sensor_model import LikelihoodField, SensorModelConfig, select_beams
from planar_geometry import OdometrySample, Pose, compose, odometry_at, relative
from planar_map import GridMap

FloatArray = npt.NDArray[np.float64]

TIME_JUMP_NS = 1_000_000_000  # odometry this far back in time: the clock was reset


class ScanSkipped(Exception):
    """A scan the localizer could not use; the message says why."""


@dataclass(frozen=True)
class AmclConfig:
    """Everything the node's parameters set.

    Attributes:
        filter: particle counts, KLD, recovery.
        sensor: likelihood field and beams.
        motion: odometry noise.
        update_min_d: translation that triggers a filter update (m).
        update_min_a: rotation that triggers a filter update (rad).
        resample_interval: filter updates between resamplings.
        odometry_history: odometry samples kept to look up the pose at a scan's stamp.
    """

    filter: FilterConfig = field(default_factory=FilterConfig)
    sensor: SensorModelConfig = field(default_factory=SensorModelConfig)
    motion: MotionNoise = field(default_factory=MotionNoise)
    update_min_d: float = 0.25
    update_min_a: float = 0.2
    resample_interval: int = 1
    odometry_history: int = 100


@dataclass(frozen=True)
class PoseEstimate:
    """The localizer's answer for one scan.

    Attributes:
        stamp_ns: the scan's stamp.
        pose: (x, y, yaw) of base_link in map.
        covariance: 3 x 3 (x, y, yaw).
        updated: whether the filter ran on this scan.
        beams: beams the sensor model used (0 when the filter did not weigh).
    """

    stamp_ns: int
    pose: Pose
    covariance: FloatArray
    updated: bool
    beams: int


class AmclLocalizer:
    """Adaptive Monte Carlo localization on a known map.

    Attributes:
        pf: the particle filter (particles, weights, rng, pose, covariance).
        grid: the map (None until one arrives).
        odometry: recent odometry samples ``(stamp_ns, x, y, yaw)``.
        odom_at_update: the odometry pose at the last filter update (None before the first).
        force_update: run the filter on the next scan even without motion.
    """

    def __init__(self, config: AmclConfig, rng: np.random.Generator, initial_pose: Pose,
                 initial_covariance: FloatArray) -> None:
        self.config = config
        self.pf = ParticleFilter(config.filter, rng)
        self.pf.initialize_gaussian(initial_pose, initial_covariance)
        self.grid: GridMap | None = None
        self.odometry: deque[OdometrySample] = deque(maxlen=config.odometry_history)
        self.odom_at_update: Pose | None = None
        self.force_update = True
        # Caches derived from the map (rebuilt when the map object changes, e.g. after a
        # restored checkpoint replaced it).
        self._field: LikelihoodField | None = None
        self._free_cells: FloatArray | None = None

    # -- inputs ---------------------------------------------------------------------------------

    def set_map(self, grid: GridMap) -> None:
        """Take a new map; the filter keeps its particles."""
        self.grid = grid
        self._likelihood_field()

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
        """Restart the filter around ``pose`` (an initial pose); it runs on the next scan."""
        self.pf.initialize_gaussian(pose, covariance)
        self.odom_at_update = self.odometry[-1][1:] if self.odometry else None
        self.force_update = True

    def set_pose_uniform(self) -> None:
        """Global localization: particles spread over the whole free space of the map.

        Raises:
            ScanSkipped: there is no map yet.
        """
        self._likelihood_field()
        assert self._free_cells is not None and self.grid is not None
        self.pf.initialize_uniform(self._free_cells, self.grid.resolution)
        self.odom_at_update = self.odometry[-1][1:] if self.odometry else None
        self.force_update = True

    def process_scan(self, stamp_ns: int, ranges: npt.ArrayLike, angle_min: float,
                     angle_increment: float, range_min: float, range_max: float) -> PoseEstimate:
        """Run the filter on a scan if the robot moved enough; the pose at the scan's stamp.

        Raises:
            ScanSkipped: no map or no odometry yet, or the scan's geometry is unusable.
        """
        model = self._likelihood_field()
        odom = odometry_at(self.odometry, stamp_ns)
        if odom is None:
            raise ScanSkipped('no odometry yet')
        try:
            beams = select_beams(ranges, angle_min, angle_increment, range_min, range_max,
                                 self.config.sensor)
        except ValueError as err:
            raise ScanSkipped(f'unusable scan: {err}') from err
        if self.odom_at_update is None:
            self.odom_at_update = odom
            self.force_update = True
        motion = relative(self.odom_at_update, odom)
        moved = (math.hypot(motion[0], motion[1]) >= self.config.update_min_d
                 or abs(motion[2]) >= self.config.update_min_a)
        used = 0
        ran = moved or self.force_update
        if ran:
            pf = self.pf
            if moved:
                pf.predict(self.odom_at_update, odom, self.config.motion)
            self.odom_at_update = odom
            self.force_update = False
            if beams.count and pf.weigh(model.log_likelihood(pf.particles, beams)):
                used = beams.count
            pf.estimate()
            if used and pf.updates_since_resample >= self.config.resample_interval:
                pf.resample(self._free_cells, self.grid.resolution if self.grid else 0.05)
        since = relative(self.odom_at_update, odom)
        pose = compose((float(self.pf.pose[0]), float(self.pf.pose[1]), float(self.pf.pose[2])),
                       since)
        return PoseEstimate(int(stamp_ns), pose, self.pf.covariance.copy(), ran, used)

    # -- caches ---------------------------------------------------------------------------------

    def _likelihood_field(self) -> LikelihoodField:
        if self.grid is None:
            raise ScanSkipped('no map yet')
        if self._field is None or self._field.grid is not self.grid:
            self._field = LikelihoodField(self.grid, self.config.sensor)
            g = self.grid
            rows, cols = np.nonzero(g.free())
            self._free_cells = np.column_stack([g.origin_x + (cols + 0.5) * g.resolution,
                                                g.origin_y + (rows + 0.5) * g.resolution])
        return self._field
