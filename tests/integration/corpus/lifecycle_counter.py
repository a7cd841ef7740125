"""A lifecycle node, managed from outside through ~/change_state as a lifecycle manager does.

It subscribes in on_configure and counts what arrives only while active; it keeps which
numbers it counted, as runs of (counted or not, how many).
"""

import json

import rclpy
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from std_msgs.msg import Int64, String


class CounterNode(LifecycleNode):
    def __init__(self):
        super().__init__('lifecycle_counter')
        self.active = False
        self.count = 0
        self.total = 0
        self.runs = []  # [[1 if counted else 0, how many], ...]
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_timer(1.0, self.report)

    def on_configure(self, state):
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state):
        self.active = True
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state):
        self.active = False
        return TransitionCallbackReturn.SUCCESS

    def on_number(self, msg):
        self.count += 1
        counted = 1 if self.active else 0
        self.total += counted * msg.data
        if self.runs and self.runs[-1][0] == counted:
            self.runs[-1][1] += 1
        else:
            self.runs.append([counted, 1])
        self.report()

    def report(self):
        state = {'count': self.count, 'total': self.total, 'runs': self.runs}
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = CounterNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
