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
from sensor_msgs.msg import LaserScan

from lama_local_localizer import LamaConfig, LamaLocalizer, PoseEstimate, ScanSkipped
from lama_local_matcher import MatcherConfig
from planar_geometry import Pose
from planar_localizer import LATCHED, SCAN_QUEUE, LocalizerCallbacks


class LamaLocalNode(LocalizerCallbacks[PoseEstimate], Node):
    """The ROS side of the localizer: parameters, subscriptions, conversion, publishing.

    Its state is ``localizer`` and ``waiting_scans`` (see ``keyvars.yaml``); the callbacks
    are ``LocalizerCallbacks``'s, shared with amcl.
    """

    scan_skipped = ScanSkipped

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

    # -- what differs from amcl (planar_localizer.LocalizerCallbacks has the rest) ------------

    def _odometry_alone(self, estimate: PoseEstimate) -> str | None:
        return None if estimate.matched else 'too few points near the map to match'


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
