"""Fragile: sums /numbers and aborts on 13, as a node with a bug for one input would."""

import os

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64


class Fragile(Node):
    def __init__(self):
        super().__init__('fragile')
        self.total = 0
        self.create_subscription(Int64, '/numbers', self.on_number, 100)

    def on_number(self, msg):
        if msg.data == 13:
            os.abort()  # the bug
        self.total += msg.data


def main():
    rclpy.init()
    node = Fragile()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
