"""Numpy state: a histogram and a rolling window."""

import json

import numpy as np
import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class HistogramNode(Node):
    def __init__(self):
        super().__init__('histogram')
        self.histogram = np.zeros(10, dtype=np.int64)
        self.window = np.zeros(5, dtype=np.float32)
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def on_number(self, msg):
        self.histogram[msg.data % 10] += 1
        self.window = np.roll(self.window, 1)
        self.window[0] = msg.data / 3.0
        self.report()

    def report(self):
        state = {'histogram': self.histogram.tolist(), 'window': self.window.tolist()}
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = HistogramNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
