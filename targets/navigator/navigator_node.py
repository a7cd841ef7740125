"""navigator: a move_base-like navigation node (A* global planner, regulated pure pursuit).

Run::

    python targets/navigator/navigator_node.py --ros-args -p use_sim_time:=true \
        -r /map:=/ground_truth/map

Subscribes ``/map`` (nav_msgs/OccupancyGrid, latched), ``/goal_pose`` (geometry_msgs/PoseStamped
in ``map``, latched), ``/amcl_pose`` (geometry_msgs/PoseWithCovarianceStamped), ``/odom``
(nav_msgs/Odometry) and ``/scan`` (sensor_msgs/LaserScan); publishes ``/cmd_vel``
(geometry_msgs/Twist), ``/navigator/plan`` (nav_msgs/Path) and ``/navigator/status``
(std_msgs/String). The algorithm lives in ``navigator_core`` and its helpers; this file turns
messages into calls and results into messages.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np
import rclpy
import rclpy.utilities
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Twist
from nav_msgs.msg import OccupancyGrid, Odometry, Path
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan
from std_msgs.msg import String

from navigator_controller import Command, ControllerParams
from navigator_core import NavigatorCore, NavigatorParams
from navigator_costmap import GridMap, InflationParams
from navigator_geometry import Pose2D, quaternion_from_yaw, yaw_from_quaternion

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)
VOLATILE_GOAL = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                           durability=DurabilityPolicy.VOLATILE)
# Deep enough to ride out a CPU stall of a second or more: a dropped message is lost state.
SENSOR = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
LOCALIZATION = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
COMMAND = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time as integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def pose_from_msg(pose: Any) -> Pose2D:
    """geometry_msgs/Pose as a planar pose (may hold NaN: check with ``finite``)."""
    q = pose.orientation
    return Pose2D(float(pose.position.x), float(pose.position.y),
                  yaw_from_quaternion(q.x, q.y, q.z, q.w))


def finite(pose: Pose2D) -> bool:
    """Whether every component is a finite number."""
    return math.isfinite(pose.x) and math.isfinite(pose.y) and math.isfinite(pose.yaw)


def grid_from_msg(msg: OccupancyGrid) -> tuple[GridMap | None, str]:
    """An OccupancyGrid as a GridMap, or None and why it cannot be used."""
    info = msg.info
    width, height, res = int(info.width), int(info.height), float(info.resolution)
    if width <= 0 or height <= 0 or not math.isfinite(res) or res <= 0.0:
        return None, f'bad size {width} x {height} at resolution {res}'
    if len(msg.data) != width * height:
        return None, f'{len(msg.data)} cells for {width} x {height}'
    q = info.origin.orientation
    if abs(yaw_from_quaternion(q.x, q.y, q.z, q.w)) > 1e-6 or abs(q.x) + abs(q.y) > 1e-6:
        return None, 'a rotated origin is not supported'
    ox, oy = float(info.origin.position.x), float(info.origin.position.y)
    if not (math.isfinite(ox) and math.isfinite(oy)):
        return None, 'the origin is not finite'
    data = np.array(msg.data, dtype=np.int8).reshape(height, width)
    return GridMap(data, res, ox, oy, stamp_ns(msg.header.stamp)), ''


class Navigator(Node):
    """The ROS side of the navigator; its state is ``self.core`` (see keyvars.yaml)."""

    def __init__(self, **node_options: Any) -> None:
        super().__init__('navigator', **node_options)
        self.params = self._read_parameters()
        self.core = NavigatorCore(self.params)
        goal_qos = LATCHED if self.get_parameter('goal_transient_local').value else VOLATILE_GOAL
        self.cmd_pub = self.create_publisher(Twist, '/cmd_vel', COMMAND)
        self.plan_pub = self.create_publisher(Path, '/navigator/plan', LATCHED)
        self.status_pub = self.create_publisher(String, '/navigator/status', LATCHED)
        self.create_subscription(OccupancyGrid, '/map', self.on_map, LATCHED)
        self.create_subscription(PoseStamped, '/goal_pose', self.on_goal, goal_qos)
        self.create_subscription(PoseWithCovarianceStamped, '/amcl_pose', self.on_amcl_pose,
                                 LOCALIZATION)
        self.create_subscription(Odometry, '/odom', self.on_odom, SENSOR)
        self.create_subscription(LaserScan, '/scan', self.on_scan, SENSOR)
        self.create_timer(1.0, self.report)
        # What was last published: output bookkeeping, not state (a restart republishes).
        self._published_status = ''
        self._published_plans = 0

    def _read_parameters(self) -> NavigatorParams:
        """Declare every parameter with its default; the tuning they make up."""
        n, i, c = NavigatorParams(), InflationParams(), ControllerParams()

        def p(name: str, default: float) -> float:
            return float(self.declare_parameter(name, default).value)

        inflation = InflationParams(
            robot_radius=p('robot_radius', i.robot_radius),
            safety_margin=p('safety_margin', i.safety_margin),
            inflation_radius=p('inflation_radius', i.inflation_radius),
            cost_scaling=p('cost_scaling_factor', i.cost_scaling),
            cost_weight=p('cost_weight', i.cost_weight),
            unknown_is_lethal=bool(self.declare_parameter('unknown_is_lethal',
                                                          i.unknown_is_lethal).value),
        )
        controller = ControllerParams(
            max_linear=p('max_vel_x', c.max_linear),
            max_angular=p('max_vel_theta', c.max_angular),
            linear_accel=p('acc_lim_x', c.linear_accel),
            angular_accel=p('acc_lim_theta', c.angular_accel),
            lookahead=p('lookahead_distance', c.lookahead),
            rotate_threshold=p('rotate_to_heading_min_angle', c.rotate_threshold),
            min_turn_radius=p('regulated_min_radius', c.min_turn_radius),
            approach_decel=p('approach_decel', c.approach_decel),
            robot_radius=inflation.robot_radius,
            collision_margin=p('collision_margin', c.collision_margin),
            collision_horizon=p('collision_horizon', c.collision_horizon),
        )
        self.declare_parameter('goal_transient_local', True)
        return NavigatorParams(
            inflation=inflation,
            controller=controller,
            xy_goal_tolerance=p('xy_goal_tolerance', n.xy_goal_tolerance),
            yaw_goal_tolerance=p('yaw_goal_tolerance', n.yaw_goal_tolerance),
            control_period=1.0 / p('controller_frequency', 1.0 / n.control_period),
            progress_timeout=p('progress_timeout', n.progress_timeout),
            blocked_timeout=p('blocked_timeout', n.blocked_timeout),
            max_recoveries=int(self.declare_parameter('max_recoveries',
                                                      n.max_recoveries).value),
            obstacle_range=p('obstacle_range', n.obstacle_range),
            backup_distance=p('backup_distance', n.backup_distance),
            scan_offset_x=p('scan_offset_x', n.scan_offset_x),
            scan_offset_y=p('scan_offset_y', n.scan_offset_y),
        )

    # -- callbacks ---------------------------------------------------------------------------

    def on_map(self, msg: OccupancyGrid) -> None:
        """A map (latched): keep it; a different one than held makes the navigator replan."""
        grid, why = grid_from_msg(msg)
        if grid is None:
            self.get_logger().warning(f'/map: ignored: {why}')
            return
        if self.core.on_map(grid):
            h, w = grid.data.shape
            self.get_logger().info(f'/map: {w} x {h} cells at {grid.resolution} m')
        self._after()

    def on_goal(self, msg: PoseStamped) -> None:
        """A goal in ``map``: plan to it (the same goal delivered again changes nothing)."""
        goal = pose_from_msg(msg.pose)
        if msg.header.frame_id not in ('', 'map'):
            self.get_logger().warning(
                f'/goal_pose: ignored: frame {msg.header.frame_id!r}, expected map')
            return
        if not finite(goal):
            self.get_logger().warning('/goal_pose: ignored: not a finite pose')
            return
        if self.core.on_goal(stamp_ns(msg.header.stamp), goal):
            self.get_logger().info(
                f'/goal_pose: ({goal.x:.2f}, {goal.y:.2f}, {math.degrees(goal.yaw):.0f} deg)')
        self._after()

    def on_amcl_pose(self, msg: PoseWithCovarianceStamped) -> None:
        """A localization pose: update the map -> odom correction."""
        pose = pose_from_msg(msg.pose.pose)
        if not finite(pose):
            self.get_logger().warning('/amcl_pose: ignored: not a finite pose')
            return
        if not self.core.on_localization(stamp_ns(msg.header.stamp), pose):
            self.get_logger().warning('/amcl_pose: ignored: no odometry yet, or older than '
                                      'the last pose', throttle_duration_sec=5.0)

    def on_odom(self, msg: Odometry) -> None:
        """Odometry: track the pose, and run control when a step is due."""
        pose = pose_from_msg(msg.pose.pose)
        if not finite(pose):
            self.get_logger().warning('/odom: ignored: not a finite pose',
                                      throttle_duration_sec=5.0)
            return
        stamp = stamp_ns(msg.header.stamp)
        if stamp < self.core.tracker.latest_stamp_ns:
            self.get_logger().warning('/odom: ignored: older than the last odometry (did the '
                                      'clock jump back?)', throttle_duration_sec=5.0)
            return
        command = self.core.on_odometry(stamp, pose)
        if command is not None:
            self._send(command)
        self._after()

    def on_scan(self, msg: LaserScan) -> None:
        """A scan: keep its returns for the collision check and for replanning."""
        ranges = np.asarray(msg.ranges, dtype=np.float32)
        angle_min, increment = float(msg.angle_min), float(msg.angle_increment)
        if len(ranges) == 0 or not (math.isfinite(angle_min) and math.isfinite(increment)) \
                or increment == 0.0:
            self.get_logger().warning(
                f'/scan: ignored: {len(ranges)} ranges, angle_min {angle_min}, '
                f'increment {increment}', throttle_duration_sec=5.0)
            return
        self.core.on_scan(stamp_ns(msg.header.stamp), ranges, angle_min, increment,
                          float(msg.range_min), float(msg.range_max))

    # -- outputs -----------------------------------------------------------------------------

    def _send(self, command: Command) -> None:
        twist = Twist()
        twist.linear.x = float(command.linear)
        twist.angular.z = float(command.angular)
        self.cmd_pub.publish(twist)

    def _after(self) -> None:
        """Log what the core noted and publish a new plan or status."""
        log = self.get_logger()
        for level, text in self.core.notes:
            # One call site per severity: rclpy refuses a call site whose severity changes.
            if level == 'error':
                log.error(text)
            elif level == 'warn':
                log.warning(text)
            else:
                log.info(text)
        self.core.notes.clear()
        if self.core.plans_made != self._published_plans:
            self._published_plans = self.core.plans_made
            self._publish_plan()
        if self.core.status.value != self._published_status:
            self._publish_status()

    def _publish_plan(self) -> None:
        path = Path()
        path.header.frame_id = 'map'
        path.header.stamp = self.get_clock().now().to_msg()
        for x, y in self.core.plan:
            pose = PoseStamped()
            pose.header = path.header
            pose.pose.position.x = float(x)
            pose.pose.position.y = float(y)
            pose.pose.orientation.w = 1.0
            path.poses.append(pose)
        goal = self.core.goal
        if path.poses and goal is not None:
            qx, qy, qz, qw = quaternion_from_yaw(goal.yaw)
            o = path.poses[-1].pose.orientation
            o.x, o.y, o.z, o.w = qx, qy, qz, qw
        self.plan_pub.publish(path)

    def _publish_status(self) -> None:
        self._published_status = self.core.status.value
        self.status_pub.publish(String(data=self.core.status.value))

    def report(self) -> None:
        """1 Hz: republish the status and say what the navigator is waiting for."""
        self._publish_status()
        core = self.core
        if core.goal is None:
            return
        if core.grid is None:
            self.get_logger().warning('waiting for /map', throttle_duration_sec=5.0)
        elif core.pose() is None:
            self.get_logger().warning('waiting for /amcl_pose (and /odom)',
                                      throttle_duration_sec=5.0)


def main(args: list[str] | None = None) -> int:
    """Run the navigator until interrupted."""
    rclpy.init(args=args)
    node = Navigator()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.utilities.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv))
