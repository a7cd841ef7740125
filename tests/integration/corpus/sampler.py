"""A node whose 1 Hz timer samples what its subscription has counted so far.

Its output depends on which inputs each tick sees, so a recovery must replay every tick where
it fell among the messages, and keep the timer's grid afterwards: each tick on the grid its
first call drew (first call + k seconds on the node's clock), one per second, none skipped,
none twice. Every time it notes is a reading of the node's own clock.
"""

import json

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class SamplerNode(Node):
    def __init__(self):
        super().__init__('sampler')
        self.count = 0
        self.seen_ns = []  # the clock when each number was applied
        self.samples = []  # [clock at the tick, count it saw]
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.sample)

    def on_number(self, msg):
        self.count += 1
        self.seen_ns.append(self.get_clock().now().nanoseconds)
        self.report()

    def sample(self):
        self.samples.append([self.get_clock().now().nanoseconds, self.count])
        self.report()

    def report(self):
        state = {'count': self.count, 'seen_ns': self.seen_ns, 'samples': self.samples}
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = SamplerNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
