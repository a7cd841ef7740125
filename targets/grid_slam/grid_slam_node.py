"""grid_slam: hector_mapping-style 2D SLAM from laser scans alone, as a ROS 2 node.

Run it as ``python targets/grid_slam/grid_slam_node.py --ros-args -p use_sim_time:=true
-p map_start_x:=0.8 -p map_start_y:=4.25``. It subscribes ``/scan``, matches every scan against
its multi-resolution occupancy grid (no odometry), publishes the robot's pose on
``/grid_slam/pose`` (one per scan, stamped with the scan's stamp) and the map on ``/map``
(reliable, transient local) every ``map_pub_period`` seconds.
"""

from __future__ import annotations

import array
import math
from typing import Any

import numpy as np
import rclpy
import rclpy.utilities
from builtin_interfaces.msg import Time as TimeMsg
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan

from grid_slam_mapper import GridMapper, MapperConfig
from grid_slam_occupancy import known_extent, occupancy_values
from grid_slam_scan import LaserMount, ScanError, scan_to_points

MAP_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Reliable and deep: a scan dropped while the CPU is busy is a scan the map never sees.
SCAN_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
WARN_EVERY = 5.0  # s between repeats of the same warning


class GridSlamNode(Node):
    """Scan-to-map matching on a multi-resolution log-odds grid (Kohlbrecher et al. 2011).

    State (what a restart loses) lives in ``self.mapper``: the grids of every level, the
    pose, the pose of the last map update, the velocity that predicts the next scan's pose
    and the last scan's stamp. Everything else is parameters and ROS plumbing.
    """

    def __init__(self) -> None:
        super().__init__('grid_slam')
        defaults = MapperConfig()
        config = MapperConfig(
            map_resolution=self._param('map_resolution', defaults.map_resolution),
            map_size=self._param('map_size', defaults.map_size),
            map_multi_res_levels=self._param('map_multi_res_levels',
                                             defaults.map_multi_res_levels),
            map_start_x=self._param('map_start_x', defaults.map_start_x),
            map_start_y=self._param('map_start_y', defaults.map_start_y),
            map_start_yaw=self._param('map_start_yaw', defaults.map_start_yaw),
            map_update_distance_thresh=self._param('map_update_distance_thresh',
                                                   defaults.map_update_distance_thresh),
            map_update_angle_thresh=self._param('map_update_angle_thresh',
                                                defaults.map_update_angle_thresh),
            update_factor_free=self._param('update_factor_free', defaults.update_factor_free),
            update_factor_occupied=self._param('update_factor_occupied',
                                               defaults.update_factor_occupied),
            log_odds_clamp=self._param('log_odds_clamp', defaults.log_odds_clamp),
            iterations_coarse=self._param('iterations_coarse', defaults.iterations_coarse),
            iterations_fine=self._param('iterations_fine', defaults.iterations_fine),
            max_prediction_gap=self._param('max_prediction_gap', defaults.max_prediction_gap),
        )
        self._check(config)
        self.mount = LaserMount(self._param('laser_offset_x', -0.064),
                                self._param('laser_offset_y', 0.0),
                                self._param('laser_offset_yaw', 0.0))
        self.laser_min_dist = self._param('laser_min_dist', 0.12)
        self.laser_max_dist = self._param('laser_max_dist', 10.0)
        self.min_scan_points = self._param('min_scan_points', 30)
        self.map_frame = self._param('map_frame', 'map')
        map_pub_period = self._param('map_pub_period', 2.0)

        self.mapper = GridMapper(config)

        self.pose_publisher = self.create_publisher(PoseStamped, '/grid_slam/pose', 10)
        self.map_publisher = self.create_publisher(OccupancyGrid, '/map', MAP_QOS)
        self.create_subscription(LaserScan, '/scan', self.on_scan, SCAN_QOS)
        self.create_timer(map_pub_period, self.publish_map)
        self.get_logger().info(
            f'grid_slam: {config.map_size} x {config.map_size} cells of '
            f'{config.map_resolution} m, {config.map_multi_res_levels} levels, starting at '
            f'({config.map_start_x}, {config.map_start_y}, {config.map_start_yaw})')

    def _param(self, name: str, default: Any) -> Any:
        return self.declare_parameter(name, default).value

    def _check(self, config: MapperConfig) -> None:
        if config.map_size % (1 << (config.map_multi_res_levels - 1)):
            msg = (f'map_size {config.map_size} must be divisible by '
                   f'2^(map_multi_res_levels - 1) = {1 << (config.map_multi_res_levels - 1)}')
            raise ValueError(msg)
        if not 0.0 < config.update_factor_free < 0.5 < config.update_factor_occupied < 1.0:
            msg = 'need 0 < update_factor_free < 0.5 < update_factor_occupied < 1'
            raise ValueError(msg)

    def on_scan(self, msg: LaserScan) -> None:
        """Match the scan, update the map when due, publish the pose."""
        logger = self.get_logger()
        min_range, max_range = self.laser_min_dist, self.laser_max_dist
        if math.isfinite(msg.range_min):
            min_range = max(min_range, msg.range_min)
        if math.isfinite(msg.range_max) and msg.range_max > 0.0:
            max_range = min(max_range, msg.range_max)
        try:
            points = scan_to_points(msg.ranges, msg.angle_min, msg.angle_increment, min_range,
                                    max_range, self.mount)
        except ScanError as err:
            logger.warning(f'/scan: {err}; scan skipped', throttle_duration_sec=WARN_EVERY)
            return
        if len(points) < self.min_scan_points:
            logger.warning(f'/scan: only {len(points)} of {len(msg.ranges)} beams are valid '
                           f'ranges (need {self.min_scan_points}); scan skipped',
                           throttle_duration_sec=WARN_EVERY)
            return
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        self.mapper.process(points, (self.mount.x, self.mount.y), stamp_ns)
        self.pose_publisher.publish(self._pose_msg(msg.header.stamp))

    def _pose_msg(self, stamp: TimeMsg) -> PoseStamped:
        x, y, yaw = (float(v) for v in self.mapper.pose)
        out = PoseStamped()
        out.header.stamp = stamp
        out.header.frame_id = self.map_frame
        out.pose.position.x = x
        out.pose.position.y = y
        out.pose.orientation.z = math.sin(yaw / 2)
        out.pose.orientation.w = math.cos(yaw / 2)
        return out

    def publish_map(self) -> None:
        """Publish the finest level, cropped to the part that has been observed."""
        mapper = self.mapper
        if mapper.map_updates == 0 or mapper.last_stamp_ns is None:
            return
        occupancy = occupancy_values(mapper.log_odds[0])
        extent = known_extent(occupancy)
        if extent is None:
            return
        r0, r1, c0, c1 = extent
        crop = np.ascontiguousarray(occupancy[r0:r1, c0:c1])
        geometry = mapper.geometry[0]
        grid = OccupancyGrid()
        grid.header.frame_id = self.map_frame
        grid.header.stamp.sec, grid.header.stamp.nanosec = divmod(mapper.last_stamp_ns,
                                                                  1_000_000_000)
        grid.info.map_load_time = grid.header.stamp
        grid.info.resolution = geometry.resolution
        grid.info.width = c1 - c0
        grid.info.height = r1 - r0
        grid.info.origin.position.x = geometry.origin_x + c0 * geometry.resolution
        grid.info.origin.position.y = geometry.origin_y + r0 * geometry.resolution
        grid.info.origin.orientation.w = 1.0
        grid.data = array.array('b', crop.tobytes())
        self.map_publisher.publish(grid)


def main(args: list[str] | None = None) -> None:
    """Run the node until shut down."""
    rclpy.init(args=args)
    node = GridSlamNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.utilities.try_shutdown()


if __name__ == '__main__':
    main()
