"""A node whose key variable turns out to be a lock: the source does not show it."""

import threading

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64


def make_guard():
    return threading.Lock()


class Guarded(Node):
    def __init__(self):
        super().__init__('guarded')
        self.count = 0
        self.guard = make_guard()
        self.create_subscription(Int64, '/numbers', self.on_number, 10)

    def on_number(self, msg):
        with self.guard:
            self.count += 1


def main():
    rclpy.init()
    node = Guarded()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
