"""A node class deriving from another Node subclass, with its state and rclpy Time values."""

import json

import rclpy
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.time import Time
from std_msgs.msg import Int64, String


class BaseNode(Node):
    """Shared plumbing: a state publisher and a report timer."""

    def __init__(self, name):
        super().__init__(name)
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_timer(1.0, self.report)

    def report(self):
        self.pub.publish(String(data=json.dumps(self.state())))


class StampNode(BaseNode):
    def __init__(self):
        self.count = 0  # set before super().__init__, on purpose
        super().__init__('stamps')
        self.latest = Time(nanoseconds=0)
        self.span = Duration(nanoseconds=0)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        if self.count:  # an early return that never happens on a fresh node
            return

    def on_number(self, msg):
        stamp = Time(nanoseconds=msg.data * 1_000_000)
        if self.count:
            step = stamp - self.latest
            self.span = Duration(nanoseconds=self.span.nanoseconds + step.nanoseconds)
        self.latest = stamp
        self.count += 1
        self.report()

    def state(self):
        return {
            'count': self.count,
            'latest': self.latest.nanoseconds,
            'span': self.span.nanoseconds,
        }


def main():
    rclpy.init()
    node = StampNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
