"""lama_local: scan-matching localization on a known map (LaMa's loc2d), as a ROS 2 node.

Subscribes ``map`` (nav_msgs/OccupancyGrid, transient local), ``scan``, ``odom`` and
``initialpose``; publishes ``/lama_local/pose`` (PoseWithCovarianceStamped in ``map``, on every
scan). Run it as::

    python targets/lama_local/lama_local_node.py --ros-args -p use_sim_time:=true \
        -p initial_pose_x:=0.8 -p initial_pose_y:=4.25 -r /map:=/ground_truth/map

The algorithm lives in the sibling modules (``lama_local_localizer`` and below), plain numpy.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan

from lama_local_localizer import LamaConfig, LamaLocalizer, PoseEstimate, ScanSkipped
from lama_local_matcher import MatcherConfig
from planar_geometry import Pose, quaternion_from_yaw, yaw_from_quaternion
from planar_map import grid_from_values

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


class LamaLocalNode(Node):
    """The ROS side of the localizer: parameters, subscriptions, conversion, publishing.

    Its state is ``localizer`` (see ``keyvars.yaml``).
    """

    def __init__(self) -> None:
        super().__init__('lama_local')
        p = self._declare_parameters()
        self.global_frame = str(p['global_frame_id'])
        initial: Pose = (float(p['initial_pose_x']), float(p['initial_pose_y']),
                         float(p['initial_pose_yaw']))
        initial_cov = np.diag([float(p['initial_cov_xx']), float(p['initial_cov_yy']),
                               float(p['initial_cov_aa'])])
        config = LamaConfig(
            matcher=MatcherConfig(
                max_distance=float(p['l2_max']), robust_scale=float(p['robust_scale']),
                max_iterations=int(p['max_iterations']), min_points=int(p['min_points'])),
            update_min_d=float(p['update_min_d']), update_min_a=float(p['update_min_a']),
            laser=(float(p['laser_x']), float(p['laser_y']), float(p['laser_yaw'])),
            max_beams=int(p['max_beams']),
        )
        self.localizer = LamaLocalizer(config, initial, initial_cov)
        self.pose_pub = self.create_publisher(PoseWithCovarianceStamped, '/lama_local/pose', 10)
        # Scans whose stamp the odometry has not reached yet (or that came before the map),
        # oldest first: a scan is matched only with the odometry at its own stamp, so the
        # result does not depend on whether DDS delivered the scan or the odometry of the same
        # instant first.
        self.waiting_scans: deque[LaserScan] = deque(maxlen=SCAN_QUEUE)
        self.map_sub = self.create_subscription(OccupancyGrid, 'map', self.on_map, LATCHED)
        # Sensors: reliable and deep enough to ride out a CPU stall (2 s of each).
        self.odom_sub = self.create_subscription(Odometry, 'odom', self.on_odom, 100)
        self.scan_sub = self.create_subscription(LaserScan, 'scan', self.on_scan, 50)
        self.initial_pose_sub = self.create_subscription(
            PoseWithCovarianceStamped, 'initialpose', self.on_initial_pose, 10)
        self.get_logger().info(
            f'lama_local: initial pose ({initial[0]:.2f}, {initial[1]:.2f}, {initial[2]:.2f}); '
            f'waiting for {self.map_sub.topic_name}')

    def _declare_parameters(self) -> dict[str, Any]:
        defaults: dict[str, Any] = {
            'global_frame_id': 'map',
            'initial_pose_x': 0.0, 'initial_pose_y': 0.0, 'initial_pose_yaw': 0.0,
            'initial_cov_xx': 0.25, 'initial_cov_yy': 0.25,
            'initial_cov_aa': (math.pi / 12.0) ** 2,
            'update_min_d': 0.05, 'update_min_a': 0.05,
            'l2_max': 0.5, 'robust_scale': 0.1, 'max_iterations': 20, 'min_points': 20,
            'max_beams': 0,
            # base_scan in base_link (there is no TF in this system: fixed offsets).
            'laser_x': -0.064, 'laser_y': 0.0, 'laser_yaw': 0.0,
        }
        for name, value in defaults.items():
            self.declare_parameter(name, value)
        return {name: self.get_parameter(name).value for name in defaults}

    # -- callbacks ----------------------------------------------------------------------------

    def on_map(self, msg: OccupancyGrid) -> None:
        """A new map: the distance field is rebuilt."""
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
        """Restart from the given pose."""
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
        self.get_logger().info(f'{topic}: restarted at ({pose[0]:.2f}, {pose[1]:.2f}, '
                               f'{pose[2]:.2f})')

    def on_scan(self, msg: LaserScan) -> None:
        """Queue the scan; it is matched once the map and the odometry at its stamp are here."""
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
        """Match the scan if the robot moved enough; publish the pose at the scan's stamp."""
        topic = self.scan_sub.topic_name
        try:
            ranges = np.asarray(msg.ranges, dtype=np.float32)
            estimate = self.localizer.process_scan(
                stamp_ns(msg.header.stamp), ranges, float(msg.angle_min),
                float(msg.angle_increment), float(msg.range_min), float(msg.range_max))
        except ScanSkipped as err:
            self.get_logger().warning(f'{topic}: {err}; skipped',
                                      throttle_duration_sec=WARN_EVERY)
            return
        if estimate.updated and not estimate.matched:
            self.get_logger().warning(
                f'{topic}: too few points near the map to match; moved on odometry alone',
                throttle_duration_sec=WARN_EVERY)
        self._publish_pose(msg, estimate)

    # -- outputs ----------------------------------------------------------------------------------

    def _publish_pose(self, scan: LaserScan, estimate: PoseEstimate) -> None:
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


def main(args: list[str] | None = None) -> None:
    """Run the node until shut down."""
    rclpy.init(args=args)
    node = LamaLocalNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
