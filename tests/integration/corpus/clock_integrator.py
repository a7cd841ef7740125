"""An integrator that measures dt with the node's clock (an odometry node's, an EKF's step).

Each number is a velocity applied for the time since the previous one, as read by
`self.get_clock().now()` in the callback. Besides the sums it keeps, per message, how long
after its publication the clock said it was applied: a replay that let the callback read the
replay's time instead of the recorded one shows as a lag of a second or more.
"""

import json

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class ClockIntegratorNode(Node):
    def __init__(self):
        super().__init__('clock_integrator')
        self.count = 0
        self.total = 0
        self.position = 0.0
        self.last_ns = None
        self.readings = []  # (number, clock reading ns), in the order applied
        self.max_lag_ns = 0
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def on_number(self, msg, info):
        now_ns = self.get_clock().now().nanoseconds
        if self.last_ns is not None:
            self.position += msg.data * (now_ns - self.last_ns) / 1e9
        self.last_ns = now_ns
        self.count += 1
        self.total += msg.data
        self.readings.append((msg.data, now_ns))
        self.max_lag_ns = max(self.max_lag_ns, now_ns - info['source_timestamp'])
        self.report()

    def report(self):
        state = {
            'count': self.count,
            'total': self.total,
            'position': self.position,
            'readings': self.readings,
            'max_lag_ns': self.max_lag_ns,
        }
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = ClockIntegratorNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
