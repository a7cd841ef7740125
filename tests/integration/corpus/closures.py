"""Callbacks as a lambda and a closure; state in plain lists and numbers."""

import json

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class ClosureNode(Node):
    def __init__(self):
        super().__init__('closures')
        self.values = []
        self.total = 0
        self.pub = self.create_publisher(String, '/state', 10)

        def remember(msg):  # a closure over self
            self.values.append(msg.data * 2)

        self.create_subscription(
            Int64, '/numbers', lambda msg: (remember(msg), self.add(msg.data)), 100
        )
        self.create_timer(1.0, self.report)

    def add(self, n):
        self.total += n
        self.report()

    def report(self):
        self.pub.publish(String(data=json.dumps({'total': self.total, 'values': self.values})))


def main():
    rclpy.init()
    node = ClosureNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
