"""Tells what the integrator holds after count_publisher.py sent 1..N: every number once, or
what was lost or counted twice. It reads the node's own /integrator/state (latched), so it
works the same whatever RORY's method, or none.

Usage: tally.py N [TIMEOUT_S]
Prints one line and exits 0 when every number is held once, 1 otherwise, 2 when no state
came within TIMEOUT_S (default 20).
"""

import json
import sys
import time

import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile
from std_msgs.msg import String

SETTLED_S = 1.5  # the node republishes its state every second: unchanged this long, it is all


def verdict(history, n):
    """One line, the same for every run that ends the same way."""
    expected = list(range(1, n + 1))
    if history == expected:
        return 0, f'count = {n}, total = {sum(expected)}: every number once, none twice'
    if len(set(history)) < len(history):
        return 1, 'numbers counted twice'
    if not history or history[0] != 1:
        return 1, 'numbers lost: the node counted from zero again after the crash'
    return 1, 'numbers lost: those between the last checkpoint and the crash, and after it'


def main():
    n = int(sys.argv[1])
    timeout = float(sys.argv[2]) if len(sys.argv) > 2 else 20.0
    rclpy.init()
    node = rclpy.create_node('tally')
    latest = {}

    def on_state(msg):
        state = json.loads(msg.data)
        if state != latest.get('state'):
            latest.update(state=state, at=time.monotonic())

    latched = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
    node.create_subscription(String, '/integrator/state', on_state, latched)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        rclpy.spin_once(node, timeout_sec=0.1)
        state = latest.get('state')
        if state and (state['count'] >= n or time.monotonic() - latest['at'] > SETTLED_S):
            break
    node.destroy_node()
    rclpy.try_shutdown()
    if 'state' not in latest:
        print(f'integrator: no state on /integrator/state within {timeout:g} s')
        return 2
    code, line = verdict(latest['state']['history'], n)
    print(f'integrator: {line}')
    return code


if __name__ == '__main__':
    sys.exit(main())
