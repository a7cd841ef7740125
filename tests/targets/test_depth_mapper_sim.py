"""targets/depth_mapper as a real process against the real simulator, and its ROS callbacks
fed bad messages.

The run is short (30 s of real_room's route, the first lap): the quality line of the issue
(>= 90 % of the model's points within 5 cm of the geometry) holds from the first metres on,
and the pose tolerance is the offline one with room for a loaded machine.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from sensor_msgs.msg import PointCloud2, PointField

from rory_eval.harness.simrun import LATCHED, SimRun
from rory_eval.metrics import distance_to_geometry, position_errors
from sim.worlds import get_world

pytestmark = pytest.mark.ros

NODE = Path(__file__).resolve().parents[2] / 'targets' / 'depth_mapper' / 'depth_mapper_node.py'
CAMERA_X = 0.12  # camera_depth_optical_frame ahead of base_link


def base_positions(poses: list[Any]) -> list[tuple[float, float, float]]:
    """(t, x, y) of base_link from the camera poses the node publishes."""
    out = []
    for p in poses:
        q = p.pose.orientation
        # The optical z axis (the camera's view) is the third column of the rotation.
        zx = 2.0 * (q.x * q.z + q.w * q.y)
        zy = 2.0 * (q.y * q.z - q.w * q.x)
        yaw = math.atan2(zy, zx)
        t = p.header.stamp.sec + p.header.stamp.nanosec * 1e-9
        out.append((t, p.pose.position.x - CAMERA_X * math.cos(yaw),
                    p.pose.position.y - CAMERA_X * math.sin(yaw)))
    return out


def cloud_points(msg: PointCloud2) -> np.ndarray:
    return np.frombuffer(bytes(msg.data), dtype=np.float32).reshape(-1, 3)


def test_node_maps_real_room_and_tracks_the_camera(tmp_path: Path, ros_domain: int) -> None:
    world = get_world('real_room')
    duration = 30.0
    run = SimRun('real_room', tmp_path / 'run', domain_id=ros_domain, duration=duration,
                 wait_for={'/camera/depth/points': 1, '/odom': 1})
    run.add_node('depth_mapper', [
        sys.executable, str(NODE), '--ros-args', '-p', 'use_sim_time:=true',
        '-p', f'map_start_x:={world.start.x}', '-p', f'map_start_y:={world.start.y}',
        '-p', f'map_start_yaw:={world.start.yaw}'])
    run.record('/depth_mapper/pose', PoseStamped)
    run.record('/depth_mapper/cloud', PointCloud2, qos=LATCHED, keep_last=True)
    run.record('/depth_mapper/keyframes', PathMsg, qos=LATCHED, keep_last=True)
    result = run.run()
    assert result.exit_codes['depth_mapper'] is None  # still running: stopped by the harness
    assert 'Traceback' not in result.log('depth_mapper')
    poses = result.messages['/depth_mapper/pose']
    assert len(poses) >= 0.8 * duration * 5  # a pose per 5 Hz frame
    assert all(p.header.frame_id == 'map' for p in poses)
    errors = position_errors(base_positions(poses), result.ground_truth)
    assert len(errors) >= 0.8 * len(poses)
    assert float(np.median(errors)) <= 0.05 and float(errors.max()) <= 0.15
    cloud = result.last('/depth_mapper/cloud')
    assert cloud.header.frame_id == 'map' and cloud.point_step == 12
    points = cloud_points(cloud)
    distance = distance_to_geometry(world, points.astype(np.float64))
    assert len(points) > 5000
    assert float(np.mean(distance < 0.05)) >= 0.9
    assert float(np.mean(distance[points[:, 2] > 0.05] < 0.05)) >= 0.9
    assert len(result.last('/depth_mapper/keyframes').poses) >= 10
    usage = result.usage['depth_mapper']
    assert 0 < usage.cpu_seconds < usage.wall_seconds and usage.peak_rss_mb > 20


def test_callbacks_skip_bad_messages_with_a_warning(ros_domain: int) -> None:
    sys.path.insert(0, str(NODE.parent))
    from depth_mapper_node import DepthMapperNode

    rclpy.init(domain_id=ros_domain)
    try:
        node = DepthMapperNode()
        mapper = node.mapper
        bad = PointCloud2()  # no fields, no data
        bad.height, bad.width = 60, 80
        node.on_cloud(bad)
        odom = Odometry()
        odom.pose.pose.position.x = math.nan
        node.on_odom(odom)
        assert not mapper.odometry and mapper.counters['frames'] == 0
        odom = Odometry()
        odom.header.stamp.sec = 1
        odom.pose.pose.orientation.w = 1.0
        node.on_odom(odom)
        empty = PointCloud2()
        empty.header.stamp.sec = 1
        empty.height, empty.width, empty.point_step, empty.row_step = 60, 80, 12, 960
        empty.fields = [PointField(name=n, offset=4 * k, datatype=PointField.FLOAT32, count=1)
                        for k, n in enumerate('xyz')]
        empty.data = np.full((60, 80, 3), np.nan, np.float32).tobytes()
        node.on_cloud(empty)  # no usable depth: tracked on odometry, with a warning
        assert mapper.counters['frames'] == 1 and mapper.counters['empty_frames'] == 1
        node.on_cloud(empty)  # the same stamp again: skipped
        assert mapper.counters['stale_frames'] == 1
        node.on_timer()  # nothing mapped yet: nothing to publish, no error
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
