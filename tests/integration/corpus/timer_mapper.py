"""A mapper that works in a timer: the subscription only buffers, a 5 Hz timer integrates.

Each tick moves what arrived since the previous tick into one batch and notes the tick's time
on the node's clock. A tick lost in a recovery shows twice: as a gap between tick times of
more than the outage, and as batch boundaries that no tick drew.
"""

import json

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class TimerMapperNode(Node):
    def __init__(self):
        super().__init__('timer_mapper')
        self.count = 0
        self.pending = []
        self.batches = []
        self.tick_ns = []
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(0.2, self.integrate)
        self.create_timer(1.0, self.report)

    def on_number(self, msg):
        self.count += 1
        self.pending.append(msg.data)
        self.report()

    def integrate(self):
        self.tick_ns.append(self.get_clock().now().nanoseconds)
        if self.pending:
            self.batches.append(self.pending)
            self.pending = []

    def report(self):
        state = {
            'count': self.count,
            'pending': self.pending,
            'batches': self.batches,
            'tick_ns': self.tick_ns,
        }
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = TimerMapperNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
