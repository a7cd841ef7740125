"""The ROS 2 bridge: steps the simulation in real time and publishes its topics.

Threads: the main thread paces the simulation (sim time = wall time x 1.0, 10 ms ticks) and
publishes; an executor thread only receives ``/cmd_vel`` and ``/e_stop`` and hands them over
under a lock. Nothing spins on a timer, so an idle executor costs nothing, and the per-tick work
is one ``mj_step`` call (five physics steps); ``/clock`` goes out every other tick (50 Hz).

Topics, rates, QoS and frames are listed in ``sim/README.md``; the QoS profiles are defined
once, in ``sim/qos.py``, for the bridge, the driver and the tests to share. Topic names are
relative, as a ROS driver's are: ``/scan`` by default, ``/robot1/scan`` under
``rory sim ... --ros-args -r __ns:=/robot1`` (``/clock`` too, so each robot's nodes remap
``/clock`` to their own simulator's).
"""

from __future__ import annotations

import array
import contextlib
import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import rclpy
import rclpy.utilities
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import PoseStamped, Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, LaserScan, PointCloud2, PointField
from std_msgs.msg import Bool, String

from .driver import CONTROL_RATE, RouteFollower
from .maps import OccupancyMap
from .qos import CLOCK_QOS, CLOUD_QOS, CMD_VEL_QOS, EVENT_QOS, LATCHED_QOS, SENSOR_QOS
from .simulation import TICK, CollisionEvent, Frame, Simulation

MAX_LAG = 0.2  # s behind real time before the pacing gives up catching up


def _stamp(msg_time: Time, ns: int) -> None:
    msg_time.sec = ns // 1_000_000_000
    msg_time.nanosec = ns % 1_000_000_000


def _yaw_quat(q: Any, yaw: float) -> None:
    q.x = 0.0
    q.y = 0.0
    q.z = math.sin(yaw / 2)
    q.w = math.cos(yaw / 2)


@dataclass
class Stats:
    """Bookkeeping of one real-time run, for the summary."""

    cpu_seconds: float = 0.0
    wall_seconds: float = 0.0
    sim_seconds: float = 0.0
    lag_resets: int = 0
    cmd_vel_received: int = 0
    e_stop_received: int = 0
    published: dict[str, int] = field(default_factory=dict)


class SimBridge:
    """The simulator's ROS node.

    Args:
        sim: the simulation to run.
        grid: ground-truth map to latch on ``/ground_truth/map`` (None: do not publish).
        info: JSON-able description latched on ``/sim/info``.
        driver: an in-process route follower (deterministic driving; None for none).
        node_name: the node's name.
    """

    def __init__(self, sim: Simulation, *, grid: OccupancyMap | None = None,
                 info: dict[str, Any] | None = None, driver: RouteFollower | None = None,
                 node_name: str = 'mujoco_sim') -> None:
        self.sim = sim
        self.driver = driver
        self.node = Node(node_name)
        self.stats = Stats()
        self._lock = threading.Lock()
        self._cmd: tuple[float, float] | None = None
        self._cmd_count = 0
        self._estop_events: list[bool] = []
        self._stop = False
        n = self.node
        self.pub_clock = n.create_publisher(Clock, 'clock', CLOCK_QOS)
        self.pub_scan = n.create_publisher(LaserScan, 'scan', SENSOR_QOS)
        self.pub_cloud = n.create_publisher(PointCloud2, 'camera/depth/points', CLOUD_QOS)
        self.pub_info = n.create_publisher(CameraInfo, 'camera/depth/camera_info', SENSOR_QOS)
        self.pub_odom = n.create_publisher(Odometry, 'odom', SENSOR_QOS)
        self.pub_truth = n.create_publisher(PoseStamped, 'ground_truth/pose', SENSOR_QOS)
        self.pub_collisions = n.create_publisher(DiagnosticArray, 'collisions', EVENT_QOS)
        n.create_subscription(Twist, 'cmd_vel', self._on_cmd_vel, CMD_VEL_QOS)
        n.create_subscription(Bool, 'e_stop', self._on_e_stop, LATCHED_QOS)
        if grid is not None:
            self.pub_map = n.create_publisher(OccupancyGrid, 'ground_truth/map', LATCHED_QOS)
            self.pub_map.publish(self._grid_msg(grid))
        if info is not None:
            self.pub_sim_info = n.create_publisher(String, 'sim/info', LATCHED_QOS)
            self.pub_sim_info.publish(String(data=json.dumps(info, sort_keys=True)))
        self._build_messages()
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name='sim-executor', daemon=True)
        self._thread.start()

    # -- inputs (executor thread) -------------------------------------------------------------

    def _spin(self) -> None:
        with contextlib.suppress(ExternalShutdownException, KeyboardInterrupt):
            self.executor.spin()

    def _on_cmd_vel(self, msg: Twist) -> None:
        with self._lock:
            self._cmd = (float(msg.linear.x), float(msg.angular.z))
            self._cmd_count += 1

    def _on_e_stop(self, msg: Bool) -> None:
        with self._lock:
            self._estop_events.append(bool(msg.data))

    def _apply_inputs(self) -> None:
        with self._lock:
            cmd, count, estops = self._cmd, self._cmd_count, self._estop_events
            self._cmd_count = 0
            self._estop_events = []
        for on in estops:
            self.sim.set_estop(on)
            self.node.get_logger().info(f'e-stop {"ENGAGED" if on else "released"} '
                                        f'at t={self.sim.time:.2f}')
        self.stats.e_stop_received += len(estops)
        if count and cmd is not None:
            self.stats.cmd_vel_received += count
            self.sim.command(*cmd)

    # -- the loop (main thread) ----------------------------------------------------------------

    def wait_for(self, needs: dict[str, int], timeout: float) -> bool:
        """Before starting the clock, wait until each topic has that many subscribers."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and rclpy.utilities.ok():
            if all(self.node.count_subscribers(t) >= k for t, k in needs.items()):
                return True
            time.sleep(0.05)
        return False

    def request_stop(self) -> None:
        """Make ``run`` return after the current tick (safe from a signal handler)."""
        self._stop = True

    def run(self, duration: float | None = None,
            should_stop: Callable[[], bool] | None = None) -> Stats:
        """Run in real time until ``duration`` sim seconds, shutdown, or ``should_stop()``."""
        sim = self.sim
        every = round(1.0 / (CONTROL_RATE * TICK))
        anchor_wall = time.monotonic()
        anchor_tick = sim.ticks
        cpu0, wall0, sim0 = time.process_time(), anchor_wall, sim.time
        check_every = 10  # ticks between calls of should_stop()
        try:
            while rclpy.utilities.ok() and not self._stop:
                if duration is not None and sim.time >= duration - 1e-9:
                    break
                if should_stop is not None and sim.ticks % check_every == 0 and should_stop():
                    break
                target = anchor_wall + (sim.ticks + 1 - anchor_tick) * TICK
                now = time.monotonic()
                if target > now:
                    time.sleep(target - now)
                elif now - target > MAX_LAG:
                    # Starved of CPU: re-anchor rather than run fast to catch up.
                    anchor_wall, anchor_tick = now, sim.ticks + 1
                    self.stats.lag_resets += 1
                self._apply_inputs()
                if self.driver is not None and sim.ticks % every == 0 and not self.driver.done:
                    p = sim.pose()
                    sim.command(*self.driver.command(p.x, p.y, p.yaw))
                frame = sim.step()
                self._publish(frame)
        except (ExternalShutdownException, KeyboardInterrupt):
            pass
        self.stats.cpu_seconds += time.process_time() - cpu0
        self.stats.wall_seconds += time.monotonic() - wall0
        self.stats.sim_seconds += sim.time - sim0
        return self.stats

    def close(self) -> None:
        """Stop the executor and destroy the node."""
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self._thread.join(timeout=2.0)

    # -- outputs ---------------------------------------------------------------------------------

    def _count(self, topic: str) -> None:
        self.stats.published[topic] = self.stats.published.get(topic, 0) + 1

    def _build_messages(self) -> None:
        """Build every outgoing message once; each tick only fills in what changed."""
        sim = self.sim
        spec, dspec = sim.lidar.spec, sim.camera.spec
        self.msg_clock = Clock()
        scan = LaserScan()
        scan.header.frame_id = sim.robot.lidar.frame_id
        scan.angle_min = spec.angle_min
        scan.angle_max = spec.angle_max
        scan.angle_increment = spec.angle_increment
        scan.time_increment = 0.0  # every beam of a scan is taken at its stamp
        scan.scan_time = 1.0 / spec.rate
        scan.range_min = spec.range_min
        scan.range_max = spec.range_max
        self.msg_scan = scan
        cloud = PointCloud2()
        cloud.header.frame_id = sim.robot.camera.frame_id
        cloud.height, cloud.width = dspec.height, dspec.width
        cloud.fields = [
            PointField(name=name, offset=4 * k, datatype=PointField.FLOAT32, count=1)
            for k, name in enumerate('xyz')
        ]
        cloud.is_bigendian = False
        cloud.point_step = 12
        cloud.row_step = 12 * dspec.width
        cloud.is_dense = False
        self.msg_cloud = cloud
        info = CameraInfo()
        info.header.frame_id = sim.robot.camera.frame_id
        info.height, info.width = dspec.height, dspec.width
        info.distortion_model = 'plumb_bob'
        info.d = array.array('d', [0.0] * 5)
        f, cx, cy = dspec.fx, dspec.cx, dspec.cy
        info.k = [f, 0.0, cx, 0.0, f, cy, 0.0, 0.0, 1.0]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        info.p = [f, 0.0, cx, 0.0, 0.0, f, cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        self.msg_info = info
        odom = Odometry()
        odom.header.frame_id = 'odom'
        odom.child_frame_id = 'base_link'
        # Nominal uncertainties (diagonal): x, y, yaw grow with drift; z, roll, pitch unused.
        odom.pose.covariance = array.array('d', _diag([0.01, 0.01, 1e6, 1e6, 1e6, 0.03]))
        odom.twist.covariance = array.array('d', _diag([0.002, 0.002, 1e6, 1e6, 1e6, 0.01]))
        self.msg_odom = odom
        truth = PoseStamped()
        truth.header.frame_id = 'map'
        self.msg_truth = truth

    def _publish(self, frame: Frame) -> None:
        sim = self.sim
        ns = frame.stamp_ns
        if frame.clock_due:
            _stamp(self.msg_clock.clock, ns)
            self.pub_clock.publish(self.msg_clock)
        if frame.odom_due:
            o = sim.odometry
            m = self.msg_odom
            _stamp(m.header.stamp, ns)
            m.pose.pose.position.x = o.x
            m.pose.pose.position.y = o.y
            _yaw_quat(m.pose.pose.orientation, o.yaw)
            m.twist.twist.linear.x = o.v
            m.twist.twist.angular.z = o.w
            self.pub_odom.publish(m)
            p = sim.pose()
            t = self.msg_truth
            _stamp(t.header.stamp, ns)
            t.pose.position.x = p.x
            t.pose.position.y = p.y
            _yaw_quat(t.pose.orientation, p.yaw)
            self.pub_truth.publish(t)
        if frame.scan is not None:
            s = self.msg_scan
            _stamp(s.header.stamp, ns)
            s.ranges = array.array('f', frame.scan.tobytes())
            self.pub_scan.publish(s)
            self._count('/scan')
        if frame.cloud is not None:
            c = self.msg_cloud
            _stamp(c.header.stamp, ns)
            c.data = frame.cloud.tobytes()
            self.pub_cloud.publish(c)
            _stamp(self.msg_info.header.stamp, ns)
            self.pub_info.publish(self.msg_info)
            self._count('/camera/depth/points')
        for event in frame.collisions:
            self._publish_collision(event, ns)

    def _publish_collision(self, event: CollisionEvent, ns: int) -> None:
        count = len(self.sim.collisions.events)
        self.node.get_logger().warning(
            f'collision #{count}: robot hit {event.obstacle} at ({event.x:.2f}, {event.y:.2f}), '
            f't={event.time:.2f} s, {event.speed:.2f} m/s')
        msg = DiagnosticArray()
        msg.header.frame_id = 'map'
        _stamp(msg.header.stamp, ns)
        status = DiagnosticStatus()
        status.level = DiagnosticStatus.ERROR
        status.name = 'collision'
        status.hardware_id = 'robot'
        status.message = f'robot hit {event.obstacle}'
        status.values = [
            KeyValue(key='obstacle', value=event.obstacle),
            KeyValue(key='x', value=f'{event.x:.3f}'),
            KeyValue(key='y', value=f'{event.y:.3f}'),
            KeyValue(key='speed', value=f'{event.speed:.3f}'),
            KeyValue(key='count', value=str(count)),
        ]
        msg.status = [status]
        self.pub_collisions.publish(msg)
        self._count('/collisions')

    @staticmethod
    def _grid_msg(grid: OccupancyMap) -> OccupancyGrid:
        msg = OccupancyGrid()
        msg.header.frame_id = 'map'
        msg.info.resolution = float(grid.resolution)
        msg.info.width = grid.width
        msg.info.height = grid.height
        msg.info.origin.position.x = float(grid.origin_x)
        msg.info.origin.position.y = float(grid.origin_y)
        msg.info.origin.orientation.w = 1.0
        msg.data = array.array('b', grid.data.tobytes())
        return msg


def _diag(values: list[float]) -> list[float]:
    out = [0.0] * 36
    for i, v in enumerate(values):
        out[7 * i] = v
    return out
