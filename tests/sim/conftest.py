"""Fixtures for the simulator's tests: a real simulator process and a probe node to talk to it."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]


def ros_env(domain: int) -> dict[str, str]:
    """Environment of a process that must hear only this test's processes."""
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    return env


class SimProcess:
    """``python -m sim run ...`` in a child process, always reaped."""

    def __init__(self, args: list[str], domain: int, log: Path) -> None:
        self.log_path = log
        self._log = open(log, 'wb')  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(
            [sys.executable, '-m', 'sim', 'run', *args], cwd=REPO, env=ros_env(domain),
            stdout=self._log, stderr=subprocess.STDOUT,
        )

    def stop(self) -> int:
        """SIGINT, then SIGTERM, then SIGKILL; the exit status."""
        for sig, wait in ((signal.SIGINT, 5.0), (signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            if self.proc.poll() is not None:
                break
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                continue
        self._log.close()
        return int(self.proc.returncode if self.proc.returncode is not None else -9)

    def output(self) -> str:
        """What the process printed so far."""
        return self.log_path.read_text(errors='replace')


class Probe:
    """A node in its own rclpy context (this test's domain) that records what the sim sends."""

    def __init__(self, domain: int) -> None:
        os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
        import rclpy
        from geometry_msgs.msg import PoseStamped, Twist
        from nav_msgs.msg import OccupancyGrid
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.signals import SignalHandlerOptions
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import LaserScan
        from std_msgs.msg import Bool, String

        from sim.qos import CMD_VEL_QOS, LATCHED_QOS, SENSOR_QOS

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = Node('sim_test_probe', context=self.context)
        self.lock = threading.Lock()
        self.poses: list[tuple[float, float, float, float]] = []  # (t, x, y, yaw)
        self.pose_wall: list[float] = []  # monotonic time each pose arrived
        self.scans: list[Any] = []
        self.clock = -1.0
        self.clock_count = 0
        self.latched: dict[str, Any] = {}
        n = self.node
        n.create_subscription(PoseStamped, '/ground_truth/pose', self._on_pose, SENSOR_QOS)
        n.create_subscription(LaserScan, '/scan', self._on_scan, SENSOR_QOS)
        n.create_subscription(Clock, '/clock', self._on_clock, SENSOR_QOS)
        n.create_subscription(String, '/sim/info', self._latch('/sim/info'), LATCHED_QOS)
        n.create_subscription(OccupancyGrid, '/ground_truth/map', self._latch('/ground_truth/map'),
                              LATCHED_QOS)
        self.cmd_vel = n.create_publisher(Twist, '/cmd_vel', CMD_VEL_QOS)
        self.e_stop = n.create_publisher(Bool, '/e_stop', LATCHED_QOS)
        self._twist, self._bool = Twist, Bool
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(n)
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:
                if not self.context.ok():
                    return
                raise

    def _on_pose(self, msg: Any) -> None:
        q = msg.pose.orientation
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        t = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        with self.lock:
            self.poses.append((t, msg.pose.position.x, msg.pose.position.y, yaw))
            self.pose_wall.append(time.monotonic())

    def _on_scan(self, msg: Any) -> None:
        with self.lock:
            self.scans.append(msg)

    def _on_clock(self, msg: Any) -> None:
        with self.lock:
            self.clock = msg.clock.sec + msg.clock.nanosec * 1e-9
            self.clock_count += 1

    def _latch(self, topic: str) -> Callable[[Any], None]:
        def on_msg(msg: Any) -> None:
            with self.lock:
                self.latched[topic] = msg
        return on_msg

    def send_twist(self, v: float, w: float = 0.0) -> None:
        """Publish one /cmd_vel."""
        msg = self._twist()
        msg.linear.x = v
        msg.angular.z = w
        self.cmd_vel.publish(msg)

    def send_e_stop(self, on: bool) -> None:
        """Publish /e_stop (latched)."""
        self.e_stop.publish(self._bool(data=on))

    def wait_until(self, cond: Callable[[], bool], timeout: float, what: str) -> None:
        """Poll ``cond`` until true; fail naming ``what`` after ``timeout`` wall seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if cond():
                    return
            time.sleep(0.01)
        raise AssertionError(f'timed out after {timeout} s waiting for {what}')

    def sim_time_at(self, wall: float) -> float:
        """Sim time at monotonic time ``wall``, from the recent pose stamps.

        The simulator runs at real time, so wall - stamp is constant but for delivery delays;
        its minimum over the last second is the least delayed estimate (a lagging probe thread
        would make ``self.clock`` look old).
        """
        with self.lock:
            pairs = [(w, p[0]) for w, p in zip(self.pose_wall, self.poses, strict=True)
                     if wall - 1.0 <= w <= wall]
        assert pairs, 'no ground truth in the last second'
        return wall - min(w - t for w, t in pairs)

    def drive(self, v: float, w: float, sim_seconds: float) -> None:
        """Send (v, w) at 20 Hz for ``sim_seconds`` of sim time."""
        with self.lock:
            end = self.clock + sim_seconds
        while True:
            with self.lock:
                if self.clock >= end:
                    return
            self.send_twist(v, w)
            time.sleep(0.05)

    def close(self) -> None:
        """Shut the context down, join the spinner, and destroy the node.

        Shutting a context down does not end its DDS participant: that goes with the last
        node of the context. A probe left undestroyed kept its latched /e_stop (True, after
        the e-stop test) alive in this pytest worker, and a later test given the same domain
        (each worker cycles through its span of ids) heard a safe state no run of its own had
        engaged (issue 35).
        """
        self.context.try_shutdown()
        self._thread.join(timeout=2.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


@pytest.fixture
def sim_world(ros_domain: int, tmp_path: Path) -> Iterator[Callable[..., tuple[SimProcess, Probe]]]:
    """Start ``sim run`` with the given arguments plus a probe; both stopped at teardown."""
    started: list[tuple[SimProcess, Probe]] = []

    def start(*args: str) -> tuple[SimProcess, Probe]:
        probe = Probe(ros_domain)
        try:
            proc = SimProcess(list(args), ros_domain, tmp_path / 'sim.log')
        except Exception:
            probe.close()
            raise
        started.append((proc, probe))
        return proc, probe

    try:
        yield start
    finally:
        for proc, probe in started:
            probe.close()
            proc.stop()
