"""A node commanded by a service: `~/fast_mode` (std_srvs/SetBool) switches how it counts.

In fast mode each number counts double. The node keeps which mode each number was counted in,
as runs of (factor, how many), and answers each request with the requests it has had.
"""

import json

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String
from std_srvs.srv import SetBool


class ModeNode(Node):
    def __init__(self):
        super().__init__('mode_switch')
        self.factor = 1
        self.requests = 0
        self.count = 0
        self.total = 0
        self.runs = []  # [[factor, numbers counted with it], ...]
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_service(SetBool, '~/fast_mode', self.on_fast_mode)
        self.create_timer(1.0, self.report)

    def on_fast_mode(self, request, response):
        self.factor = 2 if request.data else 1
        self.requests += 1
        response.success = True
        response.message = f'request {self.requests}'
        return response

    def on_number(self, msg):
        self.count += 1
        self.total += self.factor * msg.data
        if self.runs and self.runs[-1][0] == self.factor:
            self.runs[-1][1] += 1
        else:
            self.runs.append([self.factor, 1])
        self.report()

    def report(self):
        state = {'count': self.count, 'total': self.total, 'runs': self.runs,
                 'requests': self.requests}
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = ModeNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
