"""Publishes 1, 2, ..., N on /numbers at a fixed rate: a deterministic input for the integrator.

Usage: count_publisher.py N RATE_HZ [MIN_SUBSCRIBERS | @NODE [FIRST]]
FIRST (default 1) makes it publish FIRST, ..., FIRST + N - 1. It waits for MIN_SUBSCRIBERS
(default 1) matched subscriptions, or for a subscription of the node named NODE (whatever else
reads the topic), before the first number, so the no-crash run receives all of them, then
exits 0 after the last one has been acknowledged.
"""

import sys
import time

import rclpy
from rclpy.qos import QoSProfile
from std_msgs.msg import Int64


def main():
    count, rate = int(sys.argv[1]), float(sys.argv[2])
    wanted = sys.argv[3] if len(sys.argv) > 3 else '1'
    first = int(sys.argv[4]) if len(sys.argv) > 4 else 1
    rclpy.init()
    node = rclpy.create_node('count_publisher')
    pub = node.create_publisher(Int64, '/numbers', QoSProfile(depth=1000))

    def ready():
        if wanted.startswith('@'):
            # In the graph, and every reader the graph shows matched with this publisher.
            readers = node.get_subscriptions_info_by_topic('/numbers')
            return any(info.node_name == wanted[1:] for info in readers) and (
                pub.get_subscription_count() >= len(readers))
        return pub.get_subscription_count() >= int(wanted)

    while not ready():
        time.sleep(0.01)
    time.sleep(0.2)
    start = time.monotonic()
    for i in range(1, count + 1):
        delay = start + (i - 1) / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        pub.publish(Int64(data=first + i - 1))
    pub.wait_for_all_acked(rclpy.duration.Duration(seconds=5.0))
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    main()
