"""Publishes a robot's sensor load: /scan, /odom, /points and /map at fixed rates.

Usage::

    sensor_load.py --seconds S --summary OUT.json [--subscribers N] [--match-timeout T]

Streams (rate, size of one message on the wire):

=========  ======  ========================================================
/scan       10 Hz  sensor_msgs/LaserScan, 720 beams with intensities (~5.8 kB)
/odom       50 Hz  nav_msgs/Odometry (~0.7 kB)
/points      5 Hz  sensor_msgs/PointCloud2, 10 000 points of x y z intensity
                   float32 (160 kB)
/map         1 Hz  nav_msgs/OccupancyGrid, 2000 x 2000 cells of int8 (4 MB)
=========  ======  ========================================================

It waits until every topic has N matched subscriptions (default 1; a node under ``rory
supervise`` brings a second one, the supervisor's own reader), touches ``OUT.json.started``,
publishes ``round(S x rate)`` messages per topic on a fixed schedule (a message that is late
is sent at once, never skipped, so the counts do not depend on machine load), waits until
every subscriber has acknowledged everything, and writes a JSON summary: messages published
per topic, whether each topic was acknowledged, and how long ``publish()`` took. Exit status
0 when every topic was acknowledged, 1 if not, 2 if the subscriptions never matched.

Message payloads are built once as ``array.array`` and reused with a new stamp: rclpy takes
an ``array.array`` of the field's type code as it is, where a list or bytes would be checked
element by element (a 4 MB list: ~0.13 s per assignment).
"""

from __future__ import annotations

import argparse
import array
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan, PointCloud2, PointField

SCAN_BEAMS = 720
CLOUD_POINTS = 10_000
MAP_SIDE = 2000
ACK_TIMEOUT = 10.0  # seconds for every subscriber to acknowledge the last messages


@dataclass
class Stream:
    """One topic: its publisher, rate and message, and what publishing it cost."""

    topic: str
    rate: float
    publisher: Publisher
    message: Any
    published: int = 0
    publish_ms: list[float] = field(default_factory=list)
    max_late_ms: float = 0.0


def qos(depth: int) -> QoSProfile:
    """Reliable, volatile, keep-last ``depth``: what the sink asks for."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


def make_scan() -> LaserScan:
    """A 360 degree scan of a round room, 720 beams."""
    msg = LaserScan()
    msg.header.frame_id = 'base_scan'
    msg.angle_min = -math.pi
    msg.angle_increment = 2 * math.pi / SCAN_BEAMS
    msg.angle_max = msg.angle_min + msg.angle_increment * (SCAN_BEAMS - 1)
    msg.scan_time = 0.1
    msg.time_increment = msg.scan_time / SCAN_BEAMS
    msg.range_min = 0.12
    msg.range_max = 12.0
    angles = np.linspace(-math.pi, math.pi, SCAN_BEAMS, endpoint=False)
    msg.ranges = array.array('f', (3.0 + 0.5 * np.cos(3 * angles)).astype(np.float32).tobytes())
    msg.intensities = array.array('f', np.full(SCAN_BEAMS, 100.0, np.float32).tobytes())
    return msg


def make_odom() -> Odometry:
    """Odometry with covariances, as a diff-drive base publishes it."""
    msg = Odometry()
    msg.header.frame_id = 'odom'
    msg.child_frame_id = 'base_footprint'
    msg.pose.pose.orientation.w = 1.0
    msg.pose.covariance = np.diag([1e-3, 1e-3, 1e6, 1e6, 1e6, 1e-2]).flatten()
    msg.twist.covariance = np.diag([1e-3, 1e-3, 1e6, 1e6, 1e6, 1e-2]).flatten()
    return msg


def make_cloud() -> PointCloud2:
    """10 000 points of x y z intensity (float32 each, 16 bytes a point), unordered."""
    msg = PointCloud2()
    msg.header.frame_id = 'camera_depth_optical_frame'
    msg.height = 1
    msg.width = CLOUD_POINTS
    msg.fields = [
        PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
        for i, name in enumerate(('x', 'y', 'z', 'intensity'))
    ]
    msg.is_bigendian = False
    msg.point_step = 16
    msg.row_step = msg.point_step * CLOUD_POINTS
    msg.is_dense = True
    points = np.random.default_rng(7).uniform(-5.0, 5.0, (CLOUD_POINTS, 4)).astype(np.float32)
    msg.data = array.array('B', points.tobytes())
    return msg


def make_map() -> OccupancyGrid:
    """A 2000 x 2000 grid at 5 cm (100 m x 100 m): unknown outside, free inside, walls."""
    msg = OccupancyGrid()
    msg.header.frame_id = 'map'
    msg.info.resolution = 0.05
    msg.info.width = MAP_SIDE
    msg.info.height = MAP_SIDE
    msg.info.origin.position.x = -50.0
    msg.info.origin.position.y = -50.0
    msg.info.origin.orientation.w = 1.0
    grid = np.full((MAP_SIDE, MAP_SIDE), -1, np.int8)
    grid[200:1800, 200:1800] = 0
    grid[200:1800:100, 200:1800] = 100
    msg.data = array.array('b', grid.tobytes())
    return msg


def wait_for_subscribers(streams: list[Stream], count: int, timeout: float) -> bool:
    """True once every topic has ``count`` matched subscriptions, False after ``timeout``."""
    deadline = time.monotonic() + timeout
    while any(s.publisher.get_subscription_count() < count for s in streams):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def publish_all(node: Node, streams: list[Stream], seconds: float) -> None:
    """Publish ``round(seconds x rate)`` messages per stream on a fixed schedule."""
    start = time.monotonic()
    # (due time, stream index, message number); the earliest due goes first.
    schedule = sorted(
        (start + i / s.rate, k, i)
        for k, s in enumerate(streams)
        for i in range(round(seconds * s.rate))
    )
    for due, k, _ in schedule:
        stream = streams[k]
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        else:
            stream.max_late_ms = max(stream.max_late_ms, -delay * 1000.0)
        stream.message.header.stamp = node.get_clock().now().to_msg()
        began = time.perf_counter()
        stream.publisher.publish(stream.message)
        stream.publish_ms.append((time.perf_counter() - began) * 1000.0)
        stream.published += 1


def summary(streams: list[Stream], acked: dict[str, bool], seconds: float) -> dict[str, Any]:
    """What the run did, per topic."""
    return {
        'publish_seconds': seconds,
        'topics': {
            s.topic: {
                'rate': s.rate,
                'published': s.published,
                'acked': acked.get(s.topic, False),
                'publish_ms_median': float(np.median(s.publish_ms)) if s.publish_ms else None,
                'publish_ms_max': max(s.publish_ms, default=None),
                'max_late_ms': s.max_late_ms,
            }
            for s in streams
        },
    }


def main(argv: list[str] | None = None) -> int:
    """Run the load; see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--seconds', type=float, required=True)
    parser.add_argument('--summary', type=Path, required=True)
    parser.add_argument('--subscribers', type=int, default=1)
    parser.add_argument('--match-timeout', type=float, default=20.0)
    args = parser.parse_args(argv)
    rclpy.init()
    node = rclpy.create_node('sensor_load')
    try:
        streams = [
            Stream('/scan', 10.0, node.create_publisher(LaserScan, '/scan', qos(10)),
                   make_scan()),
            Stream('/odom', 50.0, node.create_publisher(Odometry, '/odom', qos(50)),
                   make_odom()),
            Stream('/points', 5.0, node.create_publisher(PointCloud2, '/points', qos(5)),
                   make_cloud()),
            Stream('/map', 1.0, node.create_publisher(OccupancyGrid, '/map', qos(2)),
                   make_map()),
        ]
        if not wait_for_subscribers(streams, args.subscribers, args.match_timeout):
            counts = {s.topic: s.publisher.get_subscription_count() for s in streams}
            print(f'sensor_load: subscriptions never matched after {args.match_timeout:g} s '
                  f'(wanted {args.subscribers} per topic, have {counts})', file=sys.stderr)
            return 2
        # Discovery is two-way: the subscriber may not yet know this writer when the writer
        # already knows it; a short pause keeps the first messages from racing that.
        time.sleep(0.3)
        Path(f'{args.summary}.started').touch()
        began = time.monotonic()
        publish_all(node, streams, args.seconds)
        took = time.monotonic() - began
        acked = {
            s.topic: bool(s.publisher.wait_for_all_acked(Duration(seconds=ACK_TIMEOUT)))
            for s in streams
        }
        result = summary(streams, acked, took)
        tmp = args.summary.with_name(args.summary.name + '.tmp')
        tmp.write_text(json.dumps(result, indent=1))
        os.replace(tmp, args.summary)
        for topic, ok in acked.items():
            if not ok:
                print(f'sensor_load: {topic}: not acknowledged within {ACK_TIMEOUT:g} s',
                      file=sys.stderr)
        return 0 if all(acked.values()) else 1
    finally:
        node.destroy_node()
        rclpy.utilities.try_shutdown()


if __name__ == '__main__':
    sys.exit(main())
