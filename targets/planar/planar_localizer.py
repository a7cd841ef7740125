"""The ROS callbacks amcl and lama_local share: a map, odometry, initial poses and scans in, the
pose out.

Both nodes localize on a known map the same way on the ROS side: a scan waits until the map
and the odometry at its stamp are here, then goes to the localizer (amcl's particle filter,
lama_local's scan matcher), and the pose comes out at the scan's stamp. ``LocalizerCallbacks``
is that side, a mixin listed before ``Node``::

    class AmclNode(LocalizerCallbacks[PoseEstimate], Node):
        scan_skipped = ScanSkipped

The node's ``__init__`` makes what the callbacks use (the attributes annotated on
``LocalizerCallbacks``; ``localizer`` and ``waiting_scans`` are its key variables,
keyvars.yaml) and its subscriptions and publishers: ``rory-instrument`` looks for a node's
``Node`` base, key variables and topics in the node's own folder, where this file is a link to
outside (README.md). The state stays on the node; nothing here holds any.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Protocol, TypeVar

import numpy as np
import numpy.typing as npt
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.subscription import Subscription
from sensor_msgs.msg import LaserScan

from planar_geometry import OdometrySample, Pose, quaternion_from_yaw, yaw_from_quaternion
from planar_map import GridMap, grid_from_values

if TYPE_CHECKING:
    from rclpy.impl.rcutils_logger import RcutilsLogger

FloatArray = npt.NDArray[np.float64]

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                     reliability=ReliabilityPolicy.RELIABLE)
WARN_EVERY = 5.0  # seconds between repeats of the same warning
SCAN_QUEUE = 10  # scans held until odometry reaches their stamp (tf2's message filter does it)


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def covariance_3x3(cov36: Any) -> np.ndarray:
    """x, y, yaw block of a 6 x 6 row-major pose covariance."""
    c = np.asarray(cov36, dtype=np.float64).reshape(6, 6)
    return c[np.ix_((0, 1, 5), (0, 1, 5))].copy()


def covariance_36(cov3: np.ndarray) -> list[float]:
    """A 3 x 3 (x, y, yaw) covariance placed in a 6 x 6 row-major pose covariance."""
    out = np.zeros((6, 6))
    out[np.ix_((0, 1, 5), (0, 1, 5))] = cov3
    return [float(v) for v in out.ravel()]


class Estimate(Protocol):
    """What a localizer answers for a scan (each target's ``PoseEstimate``)."""

    @property
    def pose(self) -> Pose: ...

    @property
    def covariance(self) -> FloatArray: ...

    @property
    def updated(self) -> bool: ...


E = TypeVar('E', bound=Estimate)
E_co = TypeVar('E_co', bound=Estimate, covariant=True)


class Localizer(Protocol[E_co]):
    """What the callbacks call on the node's localizer (``AmclLocalizer``, ``LamaLocalizer``)."""

    @property
    def grid(self) -> GridMap | None: ...

    @property
    def odometry(self) -> Sequence[OdometrySample]: ...

    def set_map(self, grid: GridMap) -> None: ...

    def add_odometry(self, stamp_ns: int, pose: Pose) -> bool: ...

    def set_pose(self, pose: Pose, covariance: FloatArray) -> None: ...

    def process_scan(self, stamp_ns: int, ranges: npt.ArrayLike, angle_min: float,
                     angle_increment: float, range_min: float, range_max: float) -> E_co: ...


class LocalizerCallbacks(Generic[E]):
    """The subscription callbacks of a localization node and its pose output.

    The node class sets ``scan_skipped`` (and may set ``restarted``), its ``__init__`` the
    attributes annotated here, and it answers ``_odometry_alone``.
    """

    scan_skipped: ClassVar[type[Exception]]  # what the localizer raises for a scan it skips
    restarted: ClassVar[str] = 'restarted'  # the log's word for a new initial pose

    # Made by the node's __init__.
    localizer: Localizer[E]
    waiting_scans: deque[LaserScan]  # scans whose stamp the odometry has not reached yet
    global_frame: str
    pose_pub: Publisher
    map_sub: Subscription
    odom_sub: Subscription
    scan_sub: Subscription
    initial_pose_sub: Subscription

    if TYPE_CHECKING:
        def get_logger(self) -> RcutilsLogger:
            """Node's (rclpy leaves it unannotated)."""

    # -- callbacks ----------------------------------------------------------------------------

    def on_map(self, msg: OccupancyGrid) -> None:
        """A new map for the localizer; scans that waited for it go on."""
        topic = self.map_sub.topic_name
        q = msg.info.origin.orientation
        if abs(q.x) > 1e-6 or abs(q.y) > 1e-6 or abs(q.z) > 1e-6:
            self.get_logger().warning(f'{topic}: a rotated map origin is not supported; ignored')
            return
        try:
            grid = grid_from_values(msg.data, int(msg.info.width), int(msg.info.height),
                                    float(msg.info.resolution),
                                    float(msg.info.origin.position.x),
                                    float(msg.info.origin.position.y))
        except ValueError as err:
            self.get_logger().warning(f'{topic}: malformed map ({err}); ignored')
            return
        self.localizer.set_map(grid)
        self.get_logger().info(f'{topic}: map {grid.width} x {grid.height} at '
                               f'{grid.resolution} m')
        self._process_ready_scans()

    def on_odom(self, msg: Odometry) -> None:
        """Remember the odometry pose at its stamp."""
        p = msg.pose.pose
        q = p.orientation
        pose = (float(p.position.x), float(p.position.y),
                yaw_from_quaternion(q.x, q.y, q.z, q.w))
        if not all(math.isfinite(v) for v in pose):
            self.get_logger().warning(f'{self.odom_sub.topic_name}: non-finite pose; skipped',
                                      throttle_duration_sec=WARN_EVERY)
            return
        if not self.localizer.add_odometry(stamp_ns(msg.header.stamp), pose):
            self.get_logger().warning(
                f'{self.odom_sub.topic_name}: stamp older than the last one; skipped',
                throttle_duration_sec=WARN_EVERY)
            return
        self._process_ready_scans()

    def on_initial_pose(self, msg: PoseWithCovarianceStamped) -> None:
        """Restart the localizer from the given pose."""
        topic = self.initial_pose_sub.topic_name
        frame = msg.header.frame_id.lstrip('/')
        if frame and frame != self.global_frame:
            self.get_logger().warning(
                f'{topic}: pose in frame {frame!r}, expected {self.global_frame!r}; ignored')
            return
        p = msg.pose.pose
        q = p.orientation
        pose = (float(p.position.x), float(p.position.y),
                yaw_from_quaternion(q.x, q.y, q.z, q.w))
        cov = covariance_3x3(msg.pose.covariance)
        if not (all(math.isfinite(v) for v in pose) and np.isfinite(cov).all()
                and (np.diag(cov) >= 0).all()):
            self.get_logger().warning(f'{topic}: non-finite pose or bad covariance; ignored')
            return
        self.localizer.set_pose(pose, cov)
        self.get_logger().info(f'{topic}: {self.restarted} at ({pose[0]:.2f}, {pose[1]:.2f}, '
                               f'{pose[2]:.2f})')

    def on_scan(self, msg: LaserScan) -> None:
        """Queue the scan; it is used once the map and the odometry at its stamp are here."""
        if self.localizer.grid is None:
            self.get_logger().warning(
                f'{self.scan_sub.topic_name}: no map yet; scans wait for it '
                f'(the newest {SCAN_QUEUE} are kept)', throttle_duration_sec=WARN_EVERY)
        self.waiting_scans.append(msg)
        self._process_ready_scans()

    def _process_ready_scans(self) -> None:
        odometry = self.localizer.odometry
        while self.waiting_scans and self.localizer.grid is not None and odometry and (
            stamp_ns(self.waiting_scans[0].header.stamp) <= odometry[-1][0]
        ):
            self._process_scan(self.waiting_scans.popleft())

    def _process_scan(self, msg: LaserScan) -> None:
        """Update if the robot moved enough; publish the pose at the scan's stamp."""
        topic = self.scan_sub.topic_name
        try:
            ranges = np.asarray(msg.ranges, dtype=np.float32)
            estimate = self.localizer.process_scan(
                stamp_ns(msg.header.stamp), ranges, float(msg.angle_min),
                float(msg.angle_increment), float(msg.range_min), float(msg.range_max))
        except self.scan_skipped as err:
            self.get_logger().warning(f'{topic}: {err}; skipped',
                                      throttle_duration_sec=WARN_EVERY)
            return
        if estimate.updated and (why := self._odometry_alone(estimate)) is not None:
            self.get_logger().warning(f'{topic}: {why}; moved on odometry alone',
                                      throttle_duration_sec=WARN_EVERY)
        self._publish(msg, estimate)

    def _odometry_alone(self, estimate: E) -> str | None:
        """Why an update left the scan out (the pose moved on odometry alone), or None."""
        raise NotImplementedError

    # -- outputs ----------------------------------------------------------------------------------

    def _publish(self, scan: LaserScan, estimate: E) -> None:
        """What a processed scan gives: its pose (a node that publishes more extends this)."""
        self._publish_pose(scan, estimate)

    def _publish_pose(self, scan: LaserScan, estimate: E) -> None:
        out = PoseWithCovarianceStamped()
        out.header.stamp = scan.header.stamp
        out.header.frame_id = self.global_frame
        x, y, yaw = estimate.pose
        out.pose.pose.position.x = x
        out.pose.pose.position.y = y
        _, _, qz, qw = quaternion_from_yaw(yaw)
        out.pose.pose.orientation.z = qz
        out.pose.pose.orientation.w = qw
        out.pose.covariance = covariance_36(estimate.covariance)
        self.pose_pub.publish(out)
