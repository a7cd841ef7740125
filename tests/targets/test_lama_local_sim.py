"""lama_local as a real process against the real simulator (short runs)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid

from rory_eval.harness.simrun import REPO, SimRun
from rory_eval.metrics import position_errors
from sim.worlds import get_world

pytestmark = pytest.mark.ros

NODE = REPO / 'targets' / 'lama_local' / 'lama_local_node.py'

# Publishes an initial pose with x = NaN twice a second (in the run's domain).
NAN_INITIAL_POSE = """
import math, rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
rclpy.init()
node = rclpy.create_node('nan_pose')
pub = node.create_publisher(PoseWithCovarianceStamped, '/initialpose', 10)
msg = PoseWithCovarianceStamped()
msg.header.frame_id = 'map'
msg.pose.pose.position.x = math.nan
msg.pose.pose.orientation.w = 1.0
node.create_timer(0.5, lambda: pub.publish(msg))
try:
    rclpy.spin(node)
except KeyboardInterrupt:
    pass
"""


def lama_argv(world: str, map_topic: str = '/ground_truth/map') -> list[str]:
    """The node's command line for a world: sim time, its start pose, the ground-truth map."""
    start = get_world(world).start
    return [sys.executable, str(NODE), '--ros-args', '-p', 'use_sim_time:=true',
            '-p', f'initial_pose_x:={start.x}', '-p', f'initial_pose_y:={start.y}',
            '-p', f'initial_pose_yaw:={start.yaw}', '-r', f'/map:={map_topic}']


def test_lama_local_tracks_the_robot_in_the_workshop(tmp_path: Path, ros_domain: int) -> None:
    # 30 s of the workshop route: along the machines, past the big machine and turning.
    # The full-length numbers, all three worlds, are in targets/lama_local/README.md.
    run = SimRun('workshop', tmp_path / 'run', domain_id=ros_domain, duration=30.0,
                 depth=False, wait_for={'/scan': 1, '/odom': 1, '/ground_truth/map': 1})
    run.add_node('lama_local', lama_argv('workshop'))
    run.record('/lama_local/pose', PoseWithCovarianceStamped)
    result = run.run()
    poses = result.messages['/lama_local/pose']
    assert len(poses) >= 280  # one per scan
    estimates = [(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, m.pose.pose.position.x,
                  m.pose.pose.position.y) for m in poses]
    errors = position_errors(estimates, result.ground_truth)
    assert errors.size >= 250
    assert float(np.median(errors)) <= 0.15
    assert float(np.percentile(errors, 95)) <= 0.3
    last = poses[-1]
    assert last.header.frame_id == 'map'
    assert all(math.isfinite(v) for v in last.pose.covariance)
    assert last.pose.covariance[0] > 0 and last.pose.covariance[35] > 0
    usage = result.usage['lama_local']
    assert usage.cpu_seconds > 0 and usage.peak_rss_mb > 20
    assert usage.cpu_percent < 60  # well within a core (measured ~11 %, see the README)


def test_lama_local_survives_bad_input(tmp_path: Path, ros_domain: int) -> None:
    # A map whose size disagrees with its data, and an initial pose full of NaN: the node
    # warns naming the topic and keeps running (without a map it publishes nothing).
    bad_map = OccupancyGrid()
    bad_map.header.frame_id = 'map'
    bad_map.info.resolution = 0.05
    bad_map.info.width, bad_map.info.height = 10, 10
    bad_map.info.origin.orientation.w = 1.0
    bad_map.data = [0] * 7
    run = SimRun('real_room', tmp_path / 'run', domain_id=ros_domain, duration=5.0,
                 depth=False, wait_for={'/scan': 1, '/bad_map': 1, '/initialpose': 1})
    run.add_node('lama_local', lama_argv('real_room', map_topic='/bad_map'))
    # /initialpose is volatile (as RViz publishes it): sent live, by a process of its own.
    run.add_node('nan_pose', [sys.executable, '-c', NAN_INITIAL_POSE])
    run.publish_latched('/bad_map', bad_map)
    run.record('/lama_local/pose', PoseWithCovarianceStamped)
    result = run.run()
    assert result.exit_codes['lama_local'] is None  # still running when the run ended
    assert result.usage['lama_local'].cpu_seconds > 0
    log = result.log('lama_local')
    assert '/bad_map: malformed map (7 cells for a 10 x 10 grid); ignored' in log
    assert '/initialpose: non-finite pose or bad covariance; ignored' in log
    assert '/scan: no map yet; scans wait for it' in log
    assert 'Traceback' not in log
    assert not result.messages['/lama_local/pose']
