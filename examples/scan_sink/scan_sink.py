"""Scan sink: counts the laser scans it takes. The lightest node that has a state: what it
costs to take one message is what is left of it.

An ordinary rclpy node that knows nothing of RORY (``rory_eval/bench/message_cost_bench.py`` runs it
bare and under RORY).
"""

import contextlib

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile
from sensor_msgs.msg import LaserScan


class ScanSink(Node):
    """Keeps the number of scans taken and the stamp of the last one."""

    def __init__(self):
        super().__init__('scan_sink')
        self.count = 0
        self.last_stamp = 0
        self.create_subscription(LaserScan, '/scan', self.on_scan, QoSProfile(depth=1000))

    def on_scan(self, msg):
        self.count += 1
        self.last_stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec


def main():
    rclpy.init()
    node = ScanSink()
    with contextlib.suppress(KeyboardInterrupt, ExternalShutdownException):
        rclpy.spin(node)


if __name__ == '__main__':
    main()
