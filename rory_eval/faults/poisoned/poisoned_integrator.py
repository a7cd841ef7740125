"""The integrator with a bug: one number, the ROS parameter ``poison``, makes it raise.

Every time, replayed or live: a poison message, as a malformed message on a shared topic is to
every node that reads it. Run several under one supervisor (each with its own node name and
state topic, by remapping) to crash them all on the same message (common_mode_campaign.py).
"""

from __future__ import annotations

import contextlib
import json

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import Int64, String


class PoisonedIntegrator(Node):
    """Keeps a running sum of /numbers; cannot handle the number ``poison`` (0: none)."""

    def __init__(self) -> None:
        super().__init__('integrator')
        self.poison = int(self.declare_parameter('poison', 0).value)
        self.total = 0
        self.count = 0
        self.history: list[int] = []
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.state_pub = self.create_publisher(String, '/integrator/state', latched)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.publish_state)

    def on_number(self, msg: Int64) -> None:
        if self.poison and msg.data == self.poison:
            raise RuntimeError(f'cannot handle {msg.data}')
        self.total += msg.data
        self.count += 1
        self.history.append(msg.data)
        self.publish_state()

    def publish_state(self) -> None:
        state = {'count': self.count, 'total': self.total, 'history': self.history}
        self.state_pub.publish(String(data=json.dumps(state)))


def main() -> None:
    rclpy.init()
    node = PoisonedIntegrator()
    with contextlib.suppress(KeyboardInterrupt):
        rclpy.spin(node)


if __name__ == '__main__':
    main()
