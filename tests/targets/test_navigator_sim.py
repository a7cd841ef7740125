"""targets/navigator as a real process against the real simulator (``--driver none``).

The navigator gets ``/ground_truth/map`` as ``/map``, a latched goal, drifting wheel odometry,
scans, and ``/amcl_pose`` from a stand-in localization node (ground truth + 2 cm noise, 10 Hz,
40 ms late; ``rory_eval.quality.navigator.relay_main``). The runs are the paper's two
navigation cases that fit a short test: real_room's far corner, across the obstacle, and
workshop's goal behind the nine pillars (the straight line runs into one). Each run is only a
few seconds longer than the drive itself (14 s and 28 s), so "reached" means reached in time.
"""

from __future__ import annotations

import math
import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.context import Context
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import LaserScan

from rory_eval.harness.scenario import scenario_env
from rory_eval.harness.simrun import LATCHED
from rory_eval.quality.navigator import TARGET, run_goal

pytestmark = pytest.mark.ros


@pytest.mark.parametrize(('world', 'goal', 'duration'), [
    ('real_room', 'far_corner', 20.0),
    ('workshop', 'behind_pillars', 34.0),
])
def test_the_goal_is_reached_without_collision(tmp_path: Path, ros_domain: int, world: str,
                                               goal: str, duration: float) -> None:
    run = run_goal(world, goal, tmp_path / 'run', domain_id=ros_domain, duration=duration,
                   figure=False)
    log = (run.out / 'navigator.log').read_text()
    assert run.reached, f'{run.statuses}\n{log[-2000:]}'
    assert run.statuses[-3:] == ['PLANNING', 'FOLLOWING', 'REACHED']
    assert run.collisions == 0
    assert run.position_error < 0.15 and run.yaw_error < 0.2
    assert run.time_to_goal is not None and run.time_to_goal < duration
    # It drove its plan, not a detour; the plan is A* around the obstacles, not the straight
    # line.
    assert run.driven_length < 1.1 * run.astar_length
    assert run.plans >= 1
    assert run.peak_rss_mb > 20 and 0 < run.cpu_percent < 60


def test_malformed_messages_are_warned_about_and_survived(tmp_path: Path,
                                                          ros_domain: int) -> None:
    env = scenario_env(ros_domain)
    log_path = tmp_path / 'navigator.log'
    with log_path.open('wb') as log:
        proc = subprocess.Popen([sys.executable, str(TARGET.node)], env=env, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain,
               signal_handler_options=SignalHandlerOptions.NO)
    node = Node('bad_input', context=context)
    try:
        grid = OccupancyGrid()
        grid.info.width, grid.info.height, grid.info.resolution = 10, 10, 0.05
        grid.data = [0] * 7  # not 10 x 10
        map_pub = node.create_publisher(OccupancyGrid, '/map', LATCHED)
        goal_pub = node.create_publisher(PoseStamped, '/goal_pose', LATCHED)
        scan_pub = node.create_publisher(LaserScan, '/scan', 10)
        odom_pub = node.create_publisher(Odometry, '/odom', 10)
        goal = PoseStamped()
        goal.pose.position.x = math.nan
        odom = Odometry()
        odom.pose.pose.position.x = math.inf
        map_pub.publish(grid)
        goal_pub.publish(goal)
        deadline = time.monotonic() + 20.0
        text = ''
        while time.monotonic() < deadline:
            scan_pub.publish(LaserScan())  # no ranges at all
            odom_pub.publish(odom)
            time.sleep(0.2)
            text = log_path.read_text(errors='replace')
            if all(t in text for t in ('/map: ignored', '/goal_pose: ignored',
                                       '/scan: ignored', '/odom: ignored')):
                break
        assert proc.poll() is None, text
        for topic in ('/map', '/goal_pose', '/scan', '/odom'):
            assert f'{topic}: ignored' in text, text
    finally:
        node.destroy_node()  # its participant outlives a shut-down context otherwise
        context.try_shutdown()
        proc.terminate()
        proc.wait(timeout=10)
