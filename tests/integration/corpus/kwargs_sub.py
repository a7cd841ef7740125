"""create_subscription with keyword arguments; a dict and a tuple as state; info callback."""

import json

import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Int64, String


class SquaresNode(Node):
    def __init__(self):
        super().__init__('squares')
        self.squares = {}
        self.order = ()
        self.last_seq = 0
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(
            msg_type=Int64,
            topic='/numbers',
            callback=self.on_number,
            qos_profile=QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE),
        )
        self.create_timer(1.0, self.report)

    def on_number(self, msg, info):
        self.squares[msg.data] = msg.data * msg.data
        self.order = (*self.order[-9:], msg.data)
        self.last_seq = info['publication_sequence_number']
        self.report()

    def report(self):
        state = {
            'squares': sorted(self.squares.items()),
            'order': list(self.order),
            'last_seq': self.last_seq,
        }
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = SquaresNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
