"""An integrator with a bug: the number 77 makes its callback block forever (a hang)."""

import json
import time

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class Stuck(Node):
    def __init__(self):
        super().__init__('stuck')
        self.history = []
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def on_number(self, msg):
        while msg.data == 77:  # waits for a device that never answers
            time.sleep(0.5)
        self.history.append(msg.data)
        self.report()

    def report(self):
        self.pub.publish(String(data=json.dumps({'history': self.history})))


def main():
    rclpy.init()
    node = Stuck()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
