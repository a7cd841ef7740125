"""The integrator with injectable one-shot faults, for the fault campaign.

Before each number it looks for a flag file in its working directory (the supervisor runs it
in its config's folder): ``fault-raise`` makes the callback raise, ``fault-hang`` makes it
block forever. The flag is removed first, so the fault strikes once, like a glitch: the same
message replayed later goes through. SIGKILL, SIGSEGV and SIGABRT come from outside.
"""

import json
import os
import time

import rclpy
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import Int64, String


def _take(flag):
    try:
        os.remove(flag)
    except FileNotFoundError:
        return False
    return True


class Integrator(Node):
    """Keeps a running sum of /numbers."""

    def __init__(self):
        super().__init__('integrator')
        self.total = 0
        self.count = 0
        self.history = []
        latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.state_pub = self.create_publisher(String, '/integrator/state', latched)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.publish_state)

    def on_number(self, msg):
        if _take('fault-raise'):
            raise RuntimeError(f'injected fault while applying {msg.data}')
        if _take('fault-hang'):
            while True:  # a driver call that never returns
                time.sleep(1.0)
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


if __name__ == '__main__':
    main()
