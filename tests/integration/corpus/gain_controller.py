"""A controller tuned at run time: its gain is a parameter, set from outside (rqt, a script)
through the node's parameter service and copied into an attribute by its callbacks.

Only the sums are key variables; the gain is not listed: RORY keeps the node's parameters in
its checkpoints and logs the changes made after one. The node records which gain each number
was scaled by, as runs of (gain, how many).
"""

import json

import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.node import Node
from std_msgs.msg import Int64, String


class GainNode(Node):
    def __init__(self):
        super().__init__('gain_controller')
        self.declare_parameter('gain', 1.0)
        self.gain = self.get_parameter('gain').value
        self.count = 0
        self.total = 0.0
        self.gains = []  # [[gain, numbers scaled by it], ...]
        self.add_on_set_parameters_callback(self.check)
        self.add_post_set_parameters_callback(self.apply)
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def check(self, params):
        return SetParametersResult(successful=all(p.value > 0 for p in params))

    def apply(self, params):
        for p in params:
            if p.name == 'gain':
                self.gain = p.value

    def on_number(self, msg):
        self.count += 1
        self.total += self.gain * msg.data
        if self.gains and self.gains[-1][0] == self.gain:
            self.gains[-1][1] += 1
        else:
            self.gains.append([self.gain, 1])
        self.report()

    def report(self):
        state = {'count': self.count, 'total': self.total, 'gains': self.gains}
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = GainNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
