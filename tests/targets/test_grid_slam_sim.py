"""grid_slam as a real process: against the simulator, and fed bad scans."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import LaserScan

from rory_eval.harness.scenario import joining, scenario_env
from rory_eval.harness.simrun import LATCHED, REPO, SimRun
from rory_eval.metrics import grid_from_msg, map_score, position_errors
from sim.maps import ground_truth_map
from sim.sensors import LIDAR
from sim.simulation import Simulation
from sim.worlds import get_world

pytestmark = pytest.mark.ros

NODE = [sys.executable, 'targets/grid_slam/grid_slam_node.py']
DURATION = 35.0  # sim s of real_room's 80 s route: once round the obstacle and on


def stamp_of(msg: Any) -> float:
    return float(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def test_the_node_maps_the_real_room_and_tracks_its_pose(tmp_path: Path,
                                                         ros_domain: int) -> None:
    world = get_world('real_room')
    run = SimRun('real_room', tmp_path / 'run', domain_id=ros_domain, duration=DURATION,
                 depth=False)
    run.add_node('grid_slam', [*NODE, '--ros-args', '-p', 'use_sim_time:=true',
                               '-p', f'map_start_x:={world.start.x!r}',
                               '-p', f'map_start_y:={world.start.y!r}',
                               '-p', f'map_start_yaw:={float(world.start.yaw)!r}'])
    run.record('/map', OccupancyGrid, qos=LATCHED, keep_last=True)
    run.record('/grid_slam/pose', PoseStamped)
    result = run.run()
    assert result.exit_codes['grid_slam'] is None  # still running when the run ended

    poses = result.messages['/grid_slam/pose']
    stamps = [stamp_of(p) for p in poses]
    # One pose per scan (10 Hz), each stamped with its scan's stamp, in order.
    assert len(poses) >= 10 * DURATION - 5
    assert all(round(s * 10) == pytest.approx(s * 10, abs=1e-6) for s in stamps)
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)
    assert {p.header.frame_id for p in poses} == {'map'}
    errors = position_errors([(stamp_of(p), p.pose.position.x, p.pose.position.y)
                              for p in poses], result.ground_truth)
    # The whole-route bounds of the offline test (test_grid_slam_core): the live run sees the
    # same scans, so a short run must meet them too.
    assert float(np.median(errors)) <= 0.05
    assert float(errors.max()) <= 0.10

    grid = result.last('/map')
    assert grid.header.frame_id == 'map' and grid.info.resolution == pytest.approx(0.05)
    score = map_score(grid_from_msg(grid), ground_truth_map(world), tolerance=1)
    assert score.agreement >= 0.90
    assert score.iou_occupied >= 0.45
    assert score.observed_fraction >= 0.5  # most of the room after one loop

    usage = result.usage['grid_slam']
    assert 0.0 < usage.cpu_seconds < usage.wall_seconds  # well under one core
    assert usage.peak_rss_mb > 20.0
    print(f'grid_slam: {usage.cpu_percent:.1f} % CPU, {usage.peak_rss_mb:.0f} MB peak RSS, '
          f'agreement {score.agreement:.3f}, IoU {score.iou_occupied:.3f}, '
          f'median error {np.median(errors):.3f} m')


class ScanFeeder:
    """Publishes /scan and records /grid_slam/pose in this test's domain."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions

        self.context = Context()
        with joining(domain):
            rclpy.init(context=self.context, domain_id=domain,
                       signal_handler_options=SignalHandlerOptions.NO)
            self.node = Node('grid_slam_test_feeder', context=self.context)
        self.scan_publisher = self.node.create_publisher(
            LaserScan, '/scan', QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE))
        self.poses: list[PoseStamped] = []
        self.node.create_subscription(PoseStamped, '/grid_slam/pose', self.poses.append, 50)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
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

    def wait_until(self, condition: Any, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < deadline, f'timed out waiting for {what}'
            time.sleep(0.05)

    def close(self) -> None:
        self.context.try_shutdown()
        self._thread.join(timeout=2.0)
        # The participant ends with the context's last node, not with its shutdown
        # (tests/sim/conftest.py, Probe.close).
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


def scan_msg(ranges: Any, stamp_s: float, angle_min: float = LIDAR.angle_min,
             angle_increment: float = LIDAR.angle_increment) -> LaserScan:
    msg = LaserScan()
    msg.header.frame_id = 'base_scan'
    msg.header.stamp.sec = int(stamp_s)
    msg.header.stamp.nanosec = round((stamp_s % 1) * 1e9)
    msg.angle_min = angle_min
    msg.angle_increment = angle_increment
    msg.angle_max = angle_min + angle_increment * (len(ranges) - 1)
    msg.range_min = LIDAR.range_min
    msg.range_max = LIDAR.range_max
    msg.ranges = [float(r) for r in ranges]
    return msg


def test_bad_scans_are_warned_about_and_skipped(tmp_path: Path, ros_domain: int) -> None:
    sim = Simulation(get_world('office_small'), depth=False)
    good = [sim.lidar.measure(0.8, 4.25, 0.0), sim.lidar.measure(0.81, 4.25, 0.0)]
    log_path = tmp_path / 'grid_slam.log'
    feeder = ScanFeeder(ros_domain)
    with log_path.open('wb') as log:
        proc = subprocess.Popen(
            [*NODE, '--ros-args', '-p', 'map_start_x:=0.8', '-p', 'map_start_y:=4.25'],
            cwd=REPO, env=scenario_env(ros_domain), stdout=log, stderr=subprocess.STDOUT,
            start_new_session=True)
    try:
        feeder.wait_until(lambda: feeder.scan_publisher.get_subscription_count() > 0, 30.0,
                          'grid_slam to subscribe /scan')
        bad = [
            scan_msg([], 1.0),  # empty
            scan_msg([math.nan] * 360, 1.1),  # every beam dropped out
            scan_msg([math.inf] * 360, 1.2),  # nothing within range
            scan_msg(good[0], 1.3, angle_increment=0.0),
            scan_msg(good[0], 1.4, angle_min=math.nan),
        ]
        for msg in [*bad, scan_msg(good[0], 2.0), scan_msg(good[1], 2.1)]:
            feeder.scan_publisher.publish(msg)
        feeder.wait_until(lambda: len(feeder.poses) >= 2, 20.0, 'the good scans\' poses')
        time.sleep(0.5)
        assert [stamp_of(p) for p in feeder.poses] == pytest.approx([2.0, 2.1])
        moved = feeder.poses[1].pose.position.x - feeder.poses[0].pose.position.x
        assert moved == pytest.approx(0.01, abs=0.01)
        assert proc.poll() is None, 'grid_slam died'
    finally:
        feeder.close()
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGINT)
        try:
            code = proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            code = proc.wait()
    text = log_path.read_text(errors='replace')
    assert text.count('/scan: only 0 of') >= 1  # the first of the throttled repeats
    assert '/scan: bad beam angles' in text
    assert 'Traceback' not in text
    assert code == 0
