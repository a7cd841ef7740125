"""Running statistics kept in dataclasses (Welford's algorithm)."""

import json
from dataclasses import asdict, dataclass, field

import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64, String


@dataclass
class Extremes:
    low: int = 0
    high: int = 0


@dataclass
class Stats:
    count: int = 0
    mean: float = 0.0
    m2: float = 0.0
    extremes: Extremes = field(default_factory=Extremes)

    def add(self, x):
        self.count += 1
        delta = x - self.mean
        self.mean += delta / self.count
        self.m2 += delta * (x - self.mean)
        if self.count == 1:
            self.extremes = Extremes(x, x)
        else:
            self.extremes.low = min(self.extremes.low, x)
            self.extremes.high = max(self.extremes.high, x)


class StatsNode(Node):
    def __init__(self):
        super().__init__('stats')
        self.stats = Stats()
        self.pub = self.create_publisher(String, '/state', 10)
        self.create_subscription(Int64, '/numbers', self.on_number, 100)
        self.create_timer(1.0, self.report)

    def on_number(self, msg):
        self.stats.add(msg.data)
        self.report()

    def report(self):
        self.pub.publish(String(data=json.dumps(asdict(self.stats))))


def main():
    rclpy.init()
    node = StatsNode()
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass


if __name__ == '__main__':
    main()
