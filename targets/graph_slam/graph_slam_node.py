"""graph_slam: RTAB-Map-like 2D graph SLAM from wheel odometry and laser scans, a ROS 2 node.

Run it as ``python targets/graph_slam/graph_slam_node.py --ros-args -p use_sim_time:=true
-p map_start_x:=0.8 -p map_start_y:=4.25``. It subscribes ``/odom`` and ``/scan``, keeps a
graph of keyframes linked by scan-matched odometry and verified loop closures, optimises it
when a loop closes, and publishes the robot's pose on ``/graph_slam/pose`` (one per scan,
stamped with the scan's stamp, in ``map``), and every ``map_publish_period`` seconds the map
on ``/map`` (reliable, transient local), the keyframe poses as a ``nav_msgs/Path`` on
``/graph_slam/graph`` and the graph's size on ``/diagnostics``.
"""

from __future__ import annotations

import os

# numpy's OpenBLAS starts a thread per core and spins them after every call: on a robot whose
# two cores are shared, a 300 x 300 solve then costs 35 ms of CPU instead of 1.5 ms, and a
# 3 x 3 product six times what it should. One thread, unless the launch says otherwise.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import array
import math
from typing import Any

import numpy as np
import rclpy
import rclpy.utilities
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid, Odometry, Path
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan

from graph_slam_core import GraphSlam, GraphSlamConfig, OutOfOrderError, ScanOutcome
from graph_slam_graph import EdgeKind
from graph_slam_scan import ScanError, scan_to_points
from graph_slam_se2 import FloatArray

LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
# Reliable and deep enough to ride out a stall of a few seconds: a dropped scan or odometry
# message is lost state (and a loop closure with its optimisation can take a few 100 ms).
SCAN_QOS = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
ODOM_QOS = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
WARN_EVERY = 5.0  # s between repeats of the same warning
MIN_SCAN_POINTS = 20


class GraphSlamNode(Node):
    """Keyframe pose-graph SLAM (RTAB-Map-like, on 2D scans).

    State (what a restart loses) lives in ``self.slam``: keyframes (poses and scans), edges
    (measurements and information matrices), the current pose, the odometry history and the
    last scan's odometry, and the occupancy counts. Everything else is parameters and ROS
    plumbing.
    """

    def __init__(self) -> None:
        super().__init__('graph_slam')
        d = GraphSlamConfig()
        config = GraphSlamConfig(
            map_start=(self._param('map_start_x', d.map_start[0]),
                       self._param('map_start_y', d.map_start[1]),
                       self._param('map_start_yaw', d.map_start[2])),
            # base_scan in base_link (no TF here); TurtleBot3 Waffle's mount by default
            laser_pose=(self._param('laser_x', -0.064), self._param('laser_y', 0.0),
                        self._param('laser_yaw', 0.0)),
            resolution=self._param('resolution', d.resolution),
            keyframe_distance=self._param('keyframe_distance', d.keyframe_distance),
            keyframe_angle=self._param('keyframe_angle', d.keyframe_angle),
            scan_matching=self._param('scan_matching', d.scan_matching),
            loop_closure=self._param('loop_closure', d.loop_closure),
            local_keyframes=self._param('local_keyframes', d.local_keyframes),
            loop_closure_radius=self._param('loop_closure_radius', d.loop_closure_radius),
            loop_min_travel=self._param('loop_min_travel', d.loop_min_travel),
            loop_min_fitness=self._param('loop_min_fitness', d.loop_min_fitness),
            loop_max_candidates=self._param('loop_max_candidates', d.loop_max_candidates),
            loop_search_window=self._param('loop_search_window', d.loop_search_window),
            loop_search_angle=self._param('loop_search_angle', d.loop_search_angle),
            optimise_iterations=self._param('optimise_iterations', d.optimise_iterations),
        )
        self._check(config)
        self.map_frame: str = self._param('map_frame', 'map')
        self.range_min: float = self._param('laser_min_range', 0.12)
        self.range_max: float = self._param('laser_max_range', 10.0)
        map_publish_period = self._param('map_publish_period', 1.0)

        self.slam = GraphSlam(config)

        self.pose_publisher = self.create_publisher(PoseStamped, '/graph_slam/pose', 10)
        self.map_publisher = self.create_publisher(OccupancyGrid, '/map', LATCHED_QOS)
        self.graph_publisher = self.create_publisher(Path, '/graph_slam/graph', LATCHED_QOS)
        self.diagnostics_publisher = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.create_subscription(Odometry, '/odom', self.on_odometry, ODOM_QOS)
        self.create_subscription(LaserScan, '/scan', self.on_scan, SCAN_QOS)
        self.create_timer(map_publish_period, self.publish_map)
        self.get_logger().info(
            f'graph_slam: keyframes every {config.keyframe_distance} m / '
            f'{config.keyframe_angle} rad, loop closures within {config.loop_closure_radius} m '
            f'(fitness >= {config.loop_min_fitness}), {config.resolution} m cells, starting at '
            f'{config.map_start}; scan matching {"on" if config.scan_matching else "off"}, '
            f'loop closure {"on" if config.loop_closure else "off"}')

    def _param(self, name: str, default: Any) -> Any:
        return self.declare_parameter(name, default).value

    @staticmethod
    def _check(config: GraphSlamConfig) -> None:
        if config.resolution <= 0 or config.keyframe_distance <= 0 or config.keyframe_angle <= 0:
            msg = 'resolution, keyframe_distance and keyframe_angle must be positive'
            raise ValueError(msg)
        if not 0.0 < config.loop_min_fitness <= 1.0:
            msg = 'loop_min_fitness must be in (0, 1]'
            raise ValueError(msg)

    # -- callbacks --------------------------------------------------------------------------

    def on_odometry(self, msg: Odometry) -> None:
        """Keep the odometry pose (odom frame) for the scans to look up."""
        p = msg.pose.pose.position
        q = msg.pose.pose.orientation
        norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
        if not (math.isfinite(p.x) and math.isfinite(p.y) and math.isfinite(norm)) or norm < 1e-9:
            self.get_logger().warning('/odom: non-finite position or orientation; ignored',
                                      throttle_duration_sec=WARN_EVERY)
            return
        yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
        try:
            outcomes = self.slam.add_odometry(_stamp_ns(msg), float(p.x), float(p.y), yaw)
        except OutOfOrderError as err:
            self.get_logger().warning(f'/odom: {err}; ignored', throttle_duration_sec=WARN_EVERY)
            return
        self._publish(outcomes)  # scans that were waiting for this odometry

    def on_scan(self, msg: LaserScan) -> None:
        """Track the scan, add a keyframe and close loops when due, publish the pose."""
        logger = self.get_logger()
        range_min = max(self.range_min, msg.range_min) if math.isfinite(msg.range_min) \
            else self.range_min
        range_max = min(self.range_max, msg.range_max) if math.isfinite(msg.range_max) \
            and msg.range_max > 0 else self.range_max
        try:
            points = scan_to_points(msg.ranges, msg.angle_min, msg.angle_increment, range_min,
                                    range_max, self.slam.laser)
        except ScanError as err:
            logger.warning(f'/scan: {err}; scan skipped', throttle_duration_sec=WARN_EVERY)
            return
        if points.shape[0] < MIN_SCAN_POINTS:
            logger.warning(f'/scan: only {points.shape[0]} of {len(msg.ranges)} beams are valid '
                           f'ranges (need {MIN_SCAN_POINTS}); scan skipped',
                           throttle_duration_sec=WARN_EVERY)
            return
        try:
            outcomes = self.slam.add_scan(_stamp_ns(msg), points)
        except OutOfOrderError as err:
            logger.warning(f'/scan: {err}; scan skipped', throttle_duration_sec=WARN_EVERY)
            return
        self._publish(outcomes)

    def _publish(self, outcomes: list[ScanOutcome]) -> None:
        """Publish the pose of each processed scan (stamped with the scan's stamp)."""
        for outcome in outcomes:
            if outcome.pose is None:
                self.get_logger().warning(f'/scan: {outcome.skipped}; scan skipped',
                                          throttle_duration_sec=WARN_EVERY)
                continue
            self._report(outcome, outcome.stamp_ns * 1e-9)
            self.pose_publisher.publish(self._pose_msg(outcome.pose, outcome.stamp_ns))

    def _report(self, outcome: ScanOutcome, stamp: float) -> None:
        logger = self.get_logger()
        for loop in outcome.loop_closures:
            logger.info(f'loop closure at t={stamp:.2f} s: keyframe {loop.target} -> '
                        f'{loop.source} (fitness {loop.fitness:.2f}, constraint '
                        f'{loop.constraint:.2f}, correction {loop.correction:.3f} m)')
        if outcome.rejected_loops and outcome.optimisation is None:
            logger.warning(f'{outcome.rejected_loops} loop closure(s) at t={stamp:.2f} s '
                           'withdrawn: the graph could not be solved with them')
        if outcome.optimisation is not None:
            opt = outcome.optimisation
            verdict = ('rejected (an edge left off by more than loop_max_residual)'
                       if outcome.rejected_loops else 'applied')
            rebuilt = (f', grid rebuilt in {outcome.rebuild_seconds * 1e3:.1f} ms'
                       if outcome.grid_rebuilt else '')
            logger.info(f'optimisation {verdict}: {len(self.slam.keyframes)} keyframes, '
                        f'{opt.iterations} iterations, error {opt.initial_error:.2f} -> '
                        f'{opt.final_error:.2f}, keyframes moved up to '
                        f'{opt.max_pose_change:.3f} m, {outcome.optimise_seconds * 1e3:.1f} ms'
                        f'{rebuilt}')

    # -- outputs ----------------------------------------------------------------------------

    def _pose_msg(self, pose: FloatArray, stamp_ns: int) -> PoseStamped:
        out = PoseStamped()
        out.header.stamp.sec, out.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
        out.header.frame_id = self.map_frame
        _set_pose(out, pose)
        return out

    def publish_map(self) -> None:
        """Publish the map, the graph and its size (all derived from the state)."""
        slam = self.slam
        if not slam.keyframes or slam.last_scan_stamp_ns is None:
            return
        sec, nanosec = divmod(slam.last_scan_stamp_ns, 1_000_000_000)
        grid = slam.grid
        rows, cols = grid.shape
        occupancy = np.ascontiguousarray(slam.occupancy())
        msg = OccupancyGrid()
        msg.header.frame_id = self.map_frame
        msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
        msg.info.map_load_time = msg.header.stamp
        msg.info.resolution = float(grid.resolution)
        msg.info.width, msg.info.height = cols, rows
        msg.info.origin.position.x = float(grid.origin_x)
        msg.info.origin.position.y = float(grid.origin_y)
        msg.info.origin.orientation.w = 1.0
        msg.data = array.array('b', occupancy.tobytes())
        self.map_publisher.publish(msg)

        path = Path()
        path.header = msg.header
        for keyframe in slam.keyframes:
            stamped = PoseStamped()
            stamped.header.frame_id = self.map_frame
            stamped.header.stamp.sec, stamped.header.stamp.nanosec = divmod(
                keyframe.stamp_ns, 1_000_000_000)
            _set_pose(stamped, keyframe.pose)
            path.poses.append(stamped)
        self.graph_publisher.publish(path)

        kinds = {kind: 0 for kind in EdgeKind}
        for edge in slam.edges:
            kinds[edge.kind] += 1
        status = DiagnosticStatus(level=DiagnosticStatus.OK, name='graph_slam',
                                  hardware_id='', message='mapping')
        values = {'keyframes': len(slam.keyframes), 'edges': len(slam.edges),
                  **{f'{kind.value}_edges': n for kind, n in kinds.items()},
                  'loop_closures': kinds[EdgeKind.LOOP], 'map_cells': rows * cols}
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        diagnostics = DiagnosticArray()
        diagnostics.header = msg.header
        diagnostics.status = [status]
        self.diagnostics_publisher.publish(diagnostics)


def _stamp_ns(msg: Any) -> int:
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _set_pose(out: PoseStamped, pose: FloatArray) -> None:
    out.pose.position.x = float(pose[0])
    out.pose.position.y = float(pose[1])
    out.pose.orientation.z = math.sin(float(pose[2]) / 2)
    out.pose.orientation.w = math.cos(float(pose[2]) / 2)


def main(args: list[str] | None = None) -> None:
    """Run the node until shut down."""
    rclpy.init(args=args)
    node = GraphSlamNode()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.utilities.try_shutdown()


if __name__ == '__main__':
    main()
