"""An Enum state machine: IDLE -> COUNTING -> PAUSED -> COUNTING ... on the input."""

import enum
import json

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


class Phase(enum.Enum):
    IDLE = 'idle'
    COUNTING = 'counting'
    PAUSED = 'paused'


class MachineNode(Node):
    def __init__(self):
        super().__init__('machine')
        self.phase = Phase.IDLE
        self.counted = 0
        self.transitions = []  # (number, phase) pairs
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def on_number(self, msg):
        n = msg.data
        if self.phase is Phase.IDLE:
            self.go(n, Phase.COUNTING)
        elif self.phase is Phase.COUNTING and n % 17 == 0:
            self.go(n, Phase.PAUSED)
        elif self.phase is Phase.PAUSED and n % 5 == 0:
            self.go(n, Phase.COUNTING)
        if self.phase is Phase.COUNTING:
            self.counted += 1
        self.report()

    def go(self, n, phase):
        self.transitions.append((n, phase))
        self.phase = phase

    def report(self):
        state = {
            'phase': self.phase.value,
            'counted': self.counted,
            'transitions': [[n, p.value] for n, p in self.transitions],
        }
        self.pub.publish(String(data=json.dumps(state)))


def main():
    rclpy.init()
    node = MachineNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
