"""Integrator: sums the numbers it receives on /numbers.

A small stateful node written the way ROS developers write nodes; it knows nothing of RORY.
Its state (total, count, history) is exactly what a respawn loses. It publishes that state on
/integrator/state after every number and once a second, as JSON.
"""

import json

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import Int64, String


class Integrator(Node):
    """Keeps a running sum of /numbers."""

    def __init__(self):
        super().__init__('integrator')
        self.total = 0
        self.count = 0
        self.history = []  # every number, in the order received
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.state_pub = self.create_publisher(String, '/integrator/state', latched)
        # Every number counts: a queue deep enough that a burst (a publisher catching up after
        # a stall) is not cut down to the newest 10 before this node can take it.
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.publish_state)

    def on_number(self, msg):
        self.total += msg.data
        self.count += 1
        self.history.append(msg.data)
        self.publish_state()

    def publish_state(self):
        state = {'count': self.count, 'total': self.total, 'history': self.history}
        self.state_pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = Integrator()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
