"""graph_slam as a real process: against the simulator, and fed bad messages."""

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
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan

from rory_eval.harness.scenario import joining, scenario_env
from rory_eval.harness.simrun import LATCHED, REPO, SimRun
from rory_eval.metrics import grid_from_msg, map_score, position_errors
from sim.maps import ground_truth_map
from sim.sensors import LIDAR
from sim.simulation import Simulation
from sim.worlds import get_world

pytestmark = pytest.mark.ros

NODE = [sys.executable, 'targets/graph_slam/graph_slam_node.py']
# office_small's route closes its loop at room D's door; offline (test_graph_slam_core) the
# first loop closures come at 43 s of sim time, on the way back round the desk island.
DURATION = 55.0


def stamp_of(msg: Any) -> float:
    return float(msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)


def start_args(world_name: str) -> list[str]:
    start = get_world(world_name).start
    return ['-p', f'map_start_x:={start.x!r}', '-p', f'map_start_y:={start.y!r}',
            '-p', f'map_start_yaw:={float(start.yaw)!r}']


def test_the_node_maps_the_office_and_closes_the_loop(tmp_path: Path, ros_domain: int) -> None:
    world = get_world('office_small')
    run = SimRun('office_small', tmp_path / 'run', domain_id=ros_domain, duration=DURATION,
                 depth=False, wait_for={'/scan': 2, '/odom': 1})
    run.add_node('graph_slam', [*NODE, '--ros-args', '-p', 'use_sim_time:=true',
                                *start_args('office_small')])
    run.record('/map', OccupancyGrid, qos=LATCHED, keep_last=True)
    run.record('/graph_slam/graph', PathMsg, qos=LATCHED, keep_last=True)
    run.record('/diagnostics', DiagnosticArray, keep_last=True)
    run.record('/graph_slam/pose', PoseStamped)
    run.record('/scan', LaserScan, qos=QoSProfile(depth=50,
                                                  reliability=ReliabilityPolicy.RELIABLE))
    result = run.run()
    assert result.exit_codes['graph_slam'] is None  # still running when the run ended

    poses = result.messages['/graph_slam/pose']
    stamps = [stamp_of(p) for p in poses]
    # One pose per scan, stamped with its scan's stamp, in order: no scan was lost (but the
    # last one's pose may come after the recorder stopped).
    scans = {stamp_of(s) for s in result.messages['/scan']}
    # (The recorder and the node stop at slightly different moments: compare up to the last
    # scan both saw.)
    last = min(max(scans), max(stamps))
    seen = {s for s in stamps if s <= last}
    assert seen <= scans and len({s for s in scans if s <= last} - seen) <= 1
    assert stamps == sorted(stamps) and {p.header.frame_id for p in poses} == {'map'}
    errors = position_errors([(stamp_of(p), p.pose.position.x, p.pose.position.y)
                              for p in poses], result.ground_truth)
    # The node sees the very scans of the offline test (--driver internal): its bounds hold.
    assert float(np.median(errors)) <= 0.05
    assert float(errors.max()) <= 0.10

    graph = result.last('/graph_slam/graph')
    assert 60 <= len(graph.poses) <= 120  # a keyframe per ~0.3 m over ~14 m, and turns
    status = result.last('/diagnostics').status[0]
    values = {kv.key: kv.value for kv in status.values}
    assert int(values['keyframes']) == len(graph.poses)
    assert int(values['loop_closures']) >= 1
    assert 'loop closure at t=' in result.log('graph_slam')

    grid = result.last('/map')
    assert grid.header.frame_id == 'map' and grid.info.resolution == pytest.approx(0.05)
    score = map_score(grid_from_msg(grid), ground_truth_map(world), tolerance=1)
    assert score.agreement >= 0.95
    assert score.iou_occupied >= 0.85
    assert score.observed_fraction >= 0.3  # the corridor and room D by 55 s (0.38)

    usage = result.usage['graph_slam']
    assert 0.0 < usage.cpu_seconds < 0.5 * usage.wall_seconds
    assert usage.peak_rss_mb > 20.0
    print(f'graph_slam: {usage.cpu_percent:.1f} % CPU, {usage.peak_rss_mb:.0f} MB peak RSS, '
          f'agreement {score.agreement:.3f}, IoU {score.iou_occupied:.3f}, median error '
          f'{np.median(errors):.3f} m, {values["loop_closures"]} loop closures')


class Feeder:
    """Publishes /odom and /scan and records /graph_slam/pose in this test's domain."""

    def __init__(self, domain: int) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node
        from rclpy.signals import SignalHandlerOptions

        self.context = Context()
        with joining(domain):
            rclpy.init(context=self.context, domain_id=domain,
                       signal_handler_options=SignalHandlerOptions.NO)
            self.node = Node('graph_slam_test_feeder', context=self.context)
        reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.scan_publisher = self.node.create_publisher(LaserScan, '/scan', reliable)
        self.odom_publisher = self.node.create_publisher(Odometry, '/odom', reliable)
        self.poses: list[PoseStamped] = []
        self.node.create_subscription(PoseStamped, '/graph_slam/pose', self.poses.append, 50)
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


def _stamp(msg: Any, stamp_s: float) -> None:
    msg.header.stamp.sec = int(stamp_s)
    msg.header.stamp.nanosec = round((stamp_s % 1) * 1e9)


def scan_msg(ranges: Any, stamp_s: float, angle_min: float = LIDAR.angle_min,
             angle_increment: float = LIDAR.angle_increment) -> LaserScan:
    msg = LaserScan()
    msg.header.frame_id = 'base_scan'
    _stamp(msg, stamp_s)
    msg.angle_min = angle_min
    msg.angle_increment = angle_increment
    msg.angle_max = angle_min + angle_increment * (len(ranges) - 1)
    msg.range_min = LIDAR.range_min
    msg.range_max = LIDAR.range_max
    msg.ranges = [float(r) for r in ranges]
    return msg


def odom_msg(x: float, stamp_s: float, qw: float = 1.0) -> Odometry:
    msg = Odometry()
    msg.header.frame_id = 'odom'
    _stamp(msg, stamp_s)
    msg.pose.pose.position.x = x
    msg.pose.pose.orientation.w = qw
    return msg


def test_bad_messages_are_warned_about_and_skipped(tmp_path: Path, ros_domain: int) -> None:
    sim = Simulation(get_world('office_small'), depth=False)
    good = [sim.lidar.measure(0.8, 4.25, 0.0), sim.lidar.measure(0.81, 4.25, 0.0)]
    log_path = tmp_path / 'graph_slam.log'
    feeder = Feeder(ros_domain)
    with log_path.open('wb') as log:
        proc = subprocess.Popen([*NODE, '--ros-args', *start_args('office_small')],
                                cwd=REPO, env=scenario_env(ros_domain), stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
    try:
        feeder.wait_until(lambda: feeder.scan_publisher.get_subscription_count() > 0
                          and feeder.odom_publisher.get_subscription_count() > 0, 30.0,
                          'graph_slam to subscribe /scan and /odom')
        feeder.scan_publisher.publish(scan_msg(good[0], 0.5))  # no odometry yet: it waits
        time.sleep(0.3)
        for msg in [odom_msg(0.0, 1.9), odom_msg(math.nan, 1.95), odom_msg(0.0, 1.96, qw=0.0),
                    odom_msg(0.0, 2.0), odom_msg(0.01, 2.1)]:
            feeder.odom_publisher.publish(msg)
        time.sleep(0.3)
        bad = [
            scan_msg([], 1.0),  # empty
            scan_msg([math.nan] * 360, 1.1),  # every beam dropped out
            scan_msg([math.inf] * 360, 1.2),  # nothing within range
            scan_msg(good[0], 1.3, angle_increment=0.0),
            scan_msg(good[0], 1.4, angle_min=math.nan),
        ]
        for msg in bad:
            feeder.scan_publisher.publish(msg)
        time.sleep(0.3)
        for msg in [scan_msg(good[0], 2.0), scan_msg(good[1], 2.1)]:
            feeder.scan_publisher.publish(msg)
        feeder.wait_until(lambda: len(feeder.poses) >= 2, 20.0, 'the good scans\' poses')
        time.sleep(0.5)
        assert [stamp_of(p) for p in feeder.poses] == pytest.approx([2.0, 2.1])
        moved = feeder.poses[1].pose.position.x - feeder.poses[0].pose.position.x
        assert moved == pytest.approx(0.01, abs=0.01)
        assert feeder.poses[0].pose.position.x == pytest.approx(0.8, abs=0.01)
        assert proc.poll() is None, 'graph_slam died'
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
    # (each warning is throttled per call site: the first of a kind is in the log)
    # the first scan waited for odometry, and what came was 1.4 s later than its stamp
    assert '/scan: nearest odometry is 1.400 s from the scan; scan skipped' in text
    assert '/odom: non-finite position or orientation; ignored' in text
    assert '/scan: the scan has no beams; scan skipped' in text
    assert '/scan: only 0 of 360 beams are valid ranges' in text
    assert 'Traceback' not in text
    assert code == 0
