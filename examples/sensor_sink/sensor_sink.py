"""Sensor sink: takes a robot's four usual sensor streams and keeps count of them.

An ordinary rclpy node that knows nothing of RORY; it stands for any node that consumes a
laser, odometry, a depth camera's point cloud and a map. Its state (how many messages of each
topic it has taken and the header stamp of the last one) is exactly what a respawn loses.

If the parameter ``report`` names a file, the node writes that state there as JSON once a
second and when it shuts down (written to a temporary file, then renamed, so a reader never
sees half a report). ``recording_bench`` reads it to learn what the node received.
"""

from __future__ import annotations

import json
import os

import rclpy
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import LaserScan, PointCloud2
from std_msgs.msg import Header


def reliable(depth: int) -> QoSProfile:
    """Reliable, volatile, keep-last ``depth``."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


# Each queue holds about one second of its stream: enough to ride out a slow callback or a
# garbage-collection pause on a busy machine without DDS overwriting a message we have not
# taken, and no deeper, since a node that stays more than a second behind its sensors is
# acting on stale data anyway.
SCAN_DEPTH = 10  # 10 Hz LaserScan
ODOM_DEPTH = 50  # 50 Hz Odometry
POINTS_DEPTH = 5  # 5 Hz PointCloud2, ~160 kB each
# Maps are usually latched (transient local, depth 1) so that a late joiner gets the current
# map; but then a reader only ever holds the newest one, and a map that arrives while the
# previous is still being handled replaces it unseen. This node counts every map, so it asks
# for reliable, volatile delivery and keeps 2 (4 MB each): the one arriving while the other
# is being handled is kept, at the price of 8 MB of queue.
MAP_DEPTH = 2


class SensorSink(Node):
    """Counts the messages of /scan, /odom, /points and /map, and keeps each last stamp."""

    TOPICS = ('/scan', '/odom', '/points', '/map')

    def __init__(self) -> None:
        super().__init__('sensor_sink')
        self.counts: dict[str, int] = {topic: 0 for topic in self.TOPICS}
        # (sec, nanosec) of the last message's header, None before the first
        self.last_stamp: dict[str, tuple[int, int] | None] = {t: None for t in self.TOPICS}
        self.report_path = str(self.declare_parameter('report', '').value)
        self.create_subscription(LaserScan, '/scan', self.on_scan, reliable(SCAN_DEPTH))
        self.create_subscription(Odometry, '/odom', self.on_odom, reliable(ODOM_DEPTH))
        self.create_subscription(PointCloud2, '/points', self.on_points, reliable(POINTS_DEPTH))
        self.create_subscription(OccupancyGrid, '/map', self.on_map, reliable(MAP_DEPTH))
        if self.report_path:
            self.create_timer(1.0, self.write_report)

    def on_scan(self, msg: LaserScan) -> None:
        self.take('/scan', msg.header)

    def on_odom(self, msg: Odometry) -> None:
        self.take('/odom', msg.header)

    def on_points(self, msg: PointCloud2) -> None:
        self.take('/points', msg.header)

    def on_map(self, msg: OccupancyGrid) -> None:
        self.take('/map', msg.header)

    def take(self, topic: str, header: Header) -> None:
        """Count one message of ``topic`` and keep its stamp."""
        self.counts[topic] += 1
        self.last_stamp[topic] = (header.stamp.sec, header.stamp.nanosec)

    def write_report(self) -> None:
        """Write the state to the ``report`` file, if one was given."""
        if not self.report_path:
            return
        report = {'counts': self.counts, 'last_stamp': self.last_stamp}
        tmp = f'{self.report_path}.tmp'
        with open(tmp, 'w') as f:
            json.dump(report, f)
        os.replace(tmp, self.report_path)


def main() -> None:
    rclpy.init()
    node = SensorSink()
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.write_report()
        node.destroy_node()
        rclpy.utilities.try_shutdown()


if __name__ == '__main__':
    main()
