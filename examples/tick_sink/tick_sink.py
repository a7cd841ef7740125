"""Tick sink: a timer at 500 Hz that reads the node's clock and counts. The lightest node that
works in a timer: what it costs to take one tick is what is left of it.

An ordinary rclpy node that knows nothing of RORY (``rory_eval/bench/message_cost_bench.py --input
tick`` runs it bare and under RORY, where each tick and its clock reading are logged).
"""

import contextlib

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

RATE = 500.0  # ticks a second


class TickSink(Node):
    """Keeps the number of ticks and the clock's time at the last one."""

    def __init__(self):
        super().__init__('tick_sink')
        self.count = 0
        self.last_ns = 0
        self.create_timer(1.0 / RATE, self.on_tick)

    def on_tick(self):
        self.count += 1
        self.last_ns = self.get_clock().now().nanoseconds


def main():
    rclpy.init()
    node = TickSink()
    with contextlib.suppress(KeyboardInterrupt, ExternalShutdownException):
        rclpy.spin(node)


if __name__ == '__main__':
    main()
