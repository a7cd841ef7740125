"""amcl: adaptive Monte Carlo localization on a known map, as a ROS 2 node.

Subscribes ``map`` (nav_msgs/OccupancyGrid, transient local), ``scan``, ``odom`` and
``initialpose``; publishes ``amcl_pose`` (PoseWithCovarianceStamped in ``map``, on every scan)
and ``particlecloud`` (PoseArray, after every filter update). Run it as::

    python targets/amcl/amcl_node.py --ros-args -p use_sim_time:=true \
        -p initial_pose_x:=0.8 -p initial_pose_y:=4.25 -r /map:=/ground_truth/map

The algorithm lives in the sibling modules (``amcl_localizer`` and below), plain numpy.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import Pose as PoseMsg
from geometry_msgs.msg import PoseArray, PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from sensor_msgs.msg import LaserScan

from amcl_filter import FilterConfig
from amcl_localizer import AmclConfig, AmclLocalizer, PoseEstimate, ScanSkipped
from amcl_motion_model import MotionNoise
from amcl_sensor_model import SensorModelConfig
from planar_geometry import Pose
from planar_localizer import LATCHED, SCAN_QUEUE, LocalizerCallbacks


class AmclNode(LocalizerCallbacks[PoseEstimate], Node):
    """The ROS side of AMCL: parameters, subscriptions, message conversion, publishing.

    Its state is ``localizer`` and ``waiting_scans`` (see ``keyvars.yaml``); the callbacks
    are ``LocalizerCallbacks``'s, shared with lama_local.
    """

    scan_skipped = ScanSkipped
    restarted = 'filter restarted'

    def __init__(self) -> None:
        super().__init__('amcl')
        p = self._declare_parameters()
        self.global_frame = str(p['global_frame_id'])
        initial: Pose = (float(p['initial_pose_x']), float(p['initial_pose_y']),
                         float(p['initial_pose_yaw']))
        initial_cov = np.diag([float(p['initial_cov_xx']), float(p['initial_cov_yy']),
                               float(p['initial_cov_aa'])])
        config = AmclConfig(
            filter=FilterConfig(
                min_particles=int(p['min_particles']), max_particles=int(p['max_particles']),
                pf_err=float(p['pf_err']), pf_z=float(p['pf_z']),
                alpha_slow=float(p['recovery_alpha_slow']),
                alpha_fast=float(p['recovery_alpha_fast'])),
            sensor=SensorModelConfig(
                z_hit=float(p['z_hit']), z_rand=float(p['z_rand']),
                sigma_hit=float(p['sigma_hit']),
                max_distance=float(p['laser_likelihood_max_dist']),
                max_beams=int(p['max_beams']), laser_x=float(p['laser_x']),
                laser_y=float(p['laser_y']), laser_yaw=float(p['laser_yaw']),
                min_range=float(p['laser_min_range']), max_range=float(p['laser_max_range'])),
            motion=MotionNoise(float(p['alpha1']), float(p['alpha2']), float(p['alpha3']),
                               float(p['alpha4'])),
            update_min_d=float(p['update_min_d']), update_min_a=float(p['update_min_a']),
            resample_interval=max(1, int(p['resample_interval'])),
        )
        self.localizer: AmclLocalizer = AmclLocalizer(
            config, np.random.default_rng(int(p['seed'])), initial, initial_cov)
        self.pose_pub = self.create_publisher(PoseWithCovarianceStamped, 'amcl_pose', LATCHED)
        self.cloud_pub = self.create_publisher(PoseArray, 'particlecloud', 2)
        # Scans whose stamp the odometry has not reached yet (or that came before the map),
        # oldest first: a scan is used only with the odometry at its own stamp, so the result
        # does not depend on whether DDS delivered the scan or the odometry of the same
        # instant first.
        self.waiting_scans: deque[LaserScan] = deque(maxlen=SCAN_QUEUE)
        self.map_sub = self.create_subscription(OccupancyGrid, 'map', self.on_map, LATCHED)
        # Sensors: reliable and deep enough to ride out a CPU stall (2 s of each).
        self.odom_sub = self.create_subscription(Odometry, 'odom', self.on_odom, 100)
        self.scan_sub = self.create_subscription(LaserScan, 'scan', self.on_scan, 50)
        self.initial_pose_sub = self.create_subscription(
            PoseWithCovarianceStamped, 'initialpose', self.on_initial_pose, 10)
        self.get_logger().info(
            f'amcl: {config.filter.min_particles}-{config.filter.max_particles} particles, '
            f'{config.sensor.max_beams} beams, initial pose ({initial[0]:.2f}, '
            f'{initial[1]:.2f}, {initial[2]:.2f}); waiting for {self.map_sub.topic_name}')

    def _declare_parameters(self) -> dict[str, Any]:
        defaults: dict[str, Any] = {
            'global_frame_id': 'map',
            'initial_pose_x': 0.0, 'initial_pose_y': 0.0, 'initial_pose_yaw': 0.0,
            'initial_cov_xx': 0.25, 'initial_cov_yy': 0.25,
            'initial_cov_aa': (math.pi / 12.0) ** 2,
            'min_particles': 500, 'max_particles': 2000, 'pf_err': 0.05, 'pf_z': 0.99,
            'recovery_alpha_slow': 0.0, 'recovery_alpha_fast': 0.0,
            'z_hit': 0.5, 'z_rand': 0.5, 'sigma_hit': 0.2, 'laser_likelihood_max_dist': 2.0,
            'max_beams': 60, 'laser_min_range': -1.0, 'laser_max_range': -1.0,
            # base_scan in base_link (there is no TF in this system: fixed offsets).
            'laser_x': -0.064, 'laser_y': 0.0, 'laser_yaw': 0.0,
            'alpha1': 0.2, 'alpha2': 0.2, 'alpha3': 0.2, 'alpha4': 0.2,
            'update_min_d': 0.25, 'update_min_a': 0.2, 'resample_interval': 1,
            'seed': 0,
        }
        for name, value in defaults.items():
            self.declare_parameter(name, value)
        return {name: self.get_parameter(name).value for name in defaults}

    # -- what differs from lama_local (planar_localizer.LocalizerCallbacks has the rest) --------

    def _odometry_alone(self, estimate: PoseEstimate) -> str | None:
        return 'no usable beams' if estimate.beams == 0 else None

    def _publish(self, scan: LaserScan, estimate: PoseEstimate) -> None:
        """The pose, and the particles after a filter update."""
        super()._publish(scan, estimate)
        if estimate.updated:
            self._publish_particles(scan)

    def _publish_particles(self, scan: LaserScan) -> None:
        if self.cloud_pub.get_subscription_count() == 0:
            return
        particles = self.localizer.pf.particles
        half = particles[:, 2] / 2.0
        qz, qw = np.sin(half), np.cos(half)
        out = PoseArray()
        out.header.stamp = scan.header.stamp
        out.header.frame_id = self.global_frame
        poses = []
        for x, y, z, w in zip(particles[:, 0].tolist(), particles[:, 1].tolist(), qz.tolist(),
                              qw.tolist(), strict=True):
            pose = PoseMsg()
            pose.position.x = x
            pose.position.y = y
            pose.orientation.z = z
            pose.orientation.w = w
            poses.append(pose)
        out.poses = poses
        self.cloud_pub.publish(out)


def main(args: list[str] | None = None) -> None:
    """Run the node until shut down."""
    rclpy.init(args=args)
    node = AmclNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
