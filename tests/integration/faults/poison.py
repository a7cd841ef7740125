"""An integrator with a bug: the number 77 makes it raise (a poison message)."""

import json

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class Fragile(Node):
    def __init__(self):
        super().__init__('fragile')
        self.history = []
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def on_number(self, msg):
        if msg.data == 77:
            raise RuntimeError('cannot handle 77')
        self.history.append(msg.data)
        self.report()

    def report(self):
        self.pub.publish(String(data=json.dumps({'history': self.history})))


def main():
    rclpy.init()
    node = Fragile()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
