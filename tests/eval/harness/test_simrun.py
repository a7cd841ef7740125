"""SimRun: the simulator and a node as real processes, a recorder, usage figures."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid
from sensor_msgs.msg import LaserScan

from rory_eval.harness.simrun import LATCHED, SimRun, SimRunError

pytestmark = pytest.mark.ros

# A node as a target would be: it subscribes /scan and echoes its stamp as a pose.
ECHO = '''
import rclpy
from rclpy.node import Node
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import LaserScan

class Echo(Node):
    def __init__(self):
        super().__init__('echo')
        self.pub = self.create_publisher(PoseStamped, '/echo/pose', 10)
        self.create_subscription(LaserScan, '/scan', self.on_scan, 10)

    def on_scan(self, msg):
        out = PoseStamped()
        out.header = msg.header
        self.pub.publish(out)

rclpy.init()
rclpy.spin(Echo())
'''


def test_a_node_runs_against_the_simulator_and_is_measured(tmp_path: Path,
                                                            ros_domain: int) -> None:
    script = tmp_path / 'echo.py'
    script.write_text(ECHO)
    run = SimRun('real_room', tmp_path / 'run', domain_id=ros_domain, duration=4.0, depth=False,
                 wait_for={'/scan': 2})
    run.add_node('echo', [sys.executable, str(script), '--ros-args', '-p', 'use_sim_time:=true'])
    run.record('/scan', LaserScan)
    run.record('/echo/pose', PoseStamped)
    run.record('/ground_truth/map', OccupancyGrid, qos=LATCHED, keep_last=True)
    result = run.run()
    scans = result.messages['/scan']
    # the clock was held until both readers were there: the first scan is at t = 0.1 s
    assert scans[0].header.stamp.sec == 0 and scans[0].header.stamp.nanosec == 100_000_000
    assert 38 <= len(scans) <= 40
    echoed = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in result.messages['/echo/pose']}
    assert len(echoed) >= len(scans) - 2
    assert result.last('/ground_truth/map').info.resolution == pytest.approx(0.05)
    assert result.summary['world'] == 'real_room'
    assert result.ground_truth[0][1:3] == (0.8, 0.8)
    usage = result.usage['echo']
    assert 0 < usage.cpu_seconds < usage.wall_seconds and usage.peak_rss_mb > 20
    # The same per role, read about once a second: one process, the node.
    assert usage.tree is not None and list(usage.tree.roles) == ['node']
    node = usage.tree.roles['node']
    assert node.processes == 1 and 0 < node.steady_cpu_seconds <= node.cpu_seconds
    assert 20 < node.pss_mb <= node.peak_rss_mb


def test_a_node_that_dies_fails_the_run_naming_it(tmp_path: Path, ros_domain: int) -> None:
    run = SimRun('real_room', tmp_path / 'run', domain_id=ros_domain, duration=4.0, depth=False)
    run.add_node('broken', [sys.executable, '-c', 'raise SystemExit("no map given")'])
    with pytest.raises(SimRunError, match=r'broken exited with 1[\s\S]*no map given'):
        run.run()
