"""The scripted driver: follows a world's waypoint route, standing in for manual driving.

``RouteFollower`` is the control law (pure Python, no ROS): turn on the spot towards the next
waypoint when it is far off the heading, otherwise drive at cruise speed while steering
proportionally. ``run_offline`` steps a ``Simulation`` synchronously with it (fast and
deterministic: the tests use it). ``main`` is the ROS node: it reads ``/ground_truth/pose`` and
publishes ``/cmd_vel`` at 20 Hz, and exits 0 when the route is done.

Run it as ``python -m sim.driver --world office_small`` next to a running ``sim run``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from .sensors import wrap
from .worlds import get_world

CONTROL_RATE = 20.0  # Hz


@dataclass
class RouteFollower:
    """Waypoint-following control law.

    Attributes:
        waypoints: the route (x, y) in the map frame.
        cruise: forward speed on straight stretches (m/s).
        max_turn: turn-rate limit (rad/s).
        turn_in_place: heading error above which the robot stops and turns (rad).
        tolerance: distance at which an intermediate waypoint counts as reached (m).
        final_tolerance: the same for the last waypoint (m).
        gain: proportional steering gain (1/s).
    """

    waypoints: Sequence[tuple[float, float]]
    cruise: float = 0.3
    max_turn: float = 1.2
    turn_in_place: float = 0.5
    tolerance: float = 0.15
    final_tolerance: float = 0.08
    gain: float = 2.0
    index: int = 0

    @property
    def done(self) -> bool:
        """Whether the last waypoint has been reached."""
        return self.index >= len(self.waypoints)

    def command(self, x: float, y: float, yaw: float) -> tuple[float, float]:
        """(linear, angular) velocity for the robot at pose (x, y, yaw)."""
        while not self.done:
            tx, ty = self.waypoints[self.index]
            last = self.index == len(self.waypoints) - 1
            dist = math.hypot(tx - x, ty - y)
            if dist > (self.final_tolerance if last else self.tolerance):
                break
            self.index += 1
        if self.done:
            return 0.0, 0.0
        tx, ty = self.waypoints[self.index]
        dist = math.hypot(tx - x, ty - y)
        err = wrap(math.atan2(ty - y, tx - x) - yaw)
        w = max(-self.max_turn, min(self.max_turn, self.gain * err))
        if abs(err) > self.turn_in_place:
            return 0.0, w
        v = self.cruise * math.cos(err)
        if self.index == len(self.waypoints) - 1:
            v = min(v, max(0.05, 0.8 * dist))  # ease into the final waypoint
        return v, w


def run_offline(
    world_name: str,
    seed: int = 0,
    *,
    cruise: float = 0.3,
    time_limit: float = 400.0,
    sensors: bool = False,
) -> dict[str, Any]:
    """Drive a world's route in a synchronous simulation; the run summary.

    Args:
        world_name: the world.
        seed: noise seed.
        cruise: driver speed (m/s).
        time_limit: give up after this much sim time (s).
        sensors: also compute lidar and depth (slower; the route does not need them).

    Returns:
        ``Simulation.summary()`` plus ``completed`` and ``route_time`` (sim s).
    """
    from .simulation import TICK, Simulation

    world = get_world(world_name)
    sim = Simulation(world, seed, lidar=sensors, depth=sensors)
    follower = RouteFollower(world.route, cruise=cruise)
    every = round(1.0 / (CONTROL_RATE * TICK))
    while not follower.done and sim.time < time_limit:
        if sim.ticks % every == 0:
            p = sim.pose()
            sim.command(*follower.command(p.x, p.y, p.yaw))
        sim.step()
    route_time = sim.time
    for _ in range(100):  # let it come to rest
        sim.step()
    summary = sim.summary()
    summary['completed'] = follower.done
    summary['route_time'] = round(route_time, 3)
    summary['path_csv'] = sim.path_csv()
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """ROS node: drive the world's route on ``/ground_truth/pose``, publish ``/cmd_vel``."""
    parser = argparse.ArgumentParser(prog='sim.driver', description=__doc__.splitlines()[0])
    parser.add_argument('--world', required=True)
    parser.add_argument('--speed', type=float, default=0.3, help='cruise speed (m/s)')
    parser.add_argument('--timeout', type=float, default=30.0,
                        help='give up when no ground truth arrives for this long (wall s)')
    args = parser.parse_args(argv)
    try:
        world = get_world(args.world)
    except KeyError as err:
        print(f'sim.driver: {err.args[0]}', file=sys.stderr)
        return 2
    return _run_node(world.route, args.speed, args.timeout, world.name)


def _run_node(route: Sequence[tuple[float, float]], speed: float, timeout: float,
              world_name: str) -> int:
    import time

    import rclpy
    import rclpy.utilities
    from geometry_msgs.msg import PoseStamped, Twist
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.qos import QoSProfile, ReliabilityPolicy

    from .qos import CMD_VEL_QOS

    rclpy.init()
    node = Node('route_driver', start_parameter_services=False)
    follower = RouteFollower(route, cruise=speed)
    latest: list[PoseStamped] = []
    heard = [time.monotonic()]

    def on_pose(pose: PoseStamped) -> None:
        latest[:] = [pose]
        heard[0] = time.monotonic()

    # Depth 1: only the newest pose matters. The node polls at the control rate instead of
    # waking for each of the 50 poses a second: rclpy's executor costs ~1 ms per wake, so this
    # is ~2.5 % of a core instead of ~6 %. The simulator runs at real time, so 50 ms of wall
    # time is 50 ms of sim time.
    node.create_subscription(PoseStamped, '/ground_truth/pose', on_pose,
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE))
    pub = node.create_publisher(Twist, '/cmd_vel', CMD_VEL_QOS)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    node.get_logger().info(f'{world_name}: driving {len(route)} waypoints at {speed} m/s')
    msg = Twist()
    last_stamp: tuple[int, int] | None = None
    code = 1
    try:
        while rclpy.utilities.ok():
            time.sleep(1.0 / CONTROL_RATE)
            executor.spin_once(timeout_sec=0.0)
            executor.spin_once(timeout_sec=0.0)
            if time.monotonic() - heard[0] > timeout:
                node.get_logger().error(f'no /ground_truth/pose for {timeout} s; giving up')
                break
            if not latest:
                continue
            pose = latest[0]
            stamp = (pose.header.stamp.sec, pose.header.stamp.nanosec)
            if stamp == last_stamp:
                continue  # no new pose (the simulator is paused or lagging): do not repeat
            last_stamp = stamp
            q = pose.pose.orientation
            yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
            v, w = follower.command(pose.pose.position.x, pose.pose.position.y, yaw)
            msg.linear.x = float(v)
            msg.angular.z = float(w)
            pub.publish(msg)
            if follower.done:
                t = stamp[0] + stamp[1] * 1e-9
                node.get_logger().info(f'{world_name}: route done at sim t={t:.2f} s')
                code = 0
                for _ in range(3):  # make sure the stop gets through
                    pub.publish(Twist())
                    time.sleep(0.02)
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.utilities.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
