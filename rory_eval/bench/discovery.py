"""How long until a restarted process is heard: DDS rediscovery after SIGKILL.

    python -m rory_eval.bench.discovery [--runs 10] [--peers 4]

A long-lived listener (like the supervisor) holds a reliable transient-local subscription;
``--peers`` idle participants stand in for the rest of the robot. A child process starts,
publishes one message at once (like a node's HELLO) and is SIGKILLed once heard; this repeats.
Printed per DDS setting: median and worst time from the child's publish to the listener's
receipt, side by side in one run.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

CHILD = r'''
import os, sys, time, rclpy
from rclpy.qos import QoSProfile, DurabilityPolicy
from std_msgs.msg import String
rclpy.init()
n = rclpy.create_node('restarted_%d' % os.getpid())
qos = QoSProfile(depth=5, durability=DurabilityPolicy.TRANSIENT_LOCAL)
p = n.create_publisher(String, '/discovery_probe', qos)
p.publish(String(data=str(time.time_ns())))
while True:
    time.sleep(1)
'''

LISTENER = r'''
import sys, time, rclpy
from rclpy.qos import QoSProfile, DurabilityPolicy
from std_msgs.msg import String
rclpy.init()
n = rclpy.create_node('listener')
qos = QoSProfile(depth=5, durability=DurabilityPolicy.TRANSIENT_LOCAL)
def on(msg):
    print('%d %d' % (int(msg.data), time.time_ns()), flush=True)
n.create_subscription(String, '/discovery_probe', on, qos)
print('ready', flush=True)
rclpy.spin(n)
'''

IDLE = r'''
import rclpy, os
rclpy.init()
n = rclpy.create_node('peer_%d' % os.getpid())
rclpy.spin(n)
'''


def _settings() -> dict[str, dict[str, str]]:
    from rory_runtime.dds import fast_rediscovery_env

    profile = fast_rediscovery_env({})['FASTRTPS_DEFAULT_PROFILES_FILE']
    return {
        # Under LOCALHOST, rmw_fastrtps keeps shared memory on in the first three whatever
        # FASTDDS_BUILTIN_TRANSPORTS says; the last is what RORY runs (UDPv4 on 127.0.0.1).
        'default (SHM+UDPv4)': {},
        'UDPv4': {'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4'},
        'UDPv4 + fast_rediscovery.xml': {
            'FASTDDS_BUILTIN_TRANSPORTS': 'UDPv4',
            'FASTRTPS_DEFAULT_PROFILES_FILE': profile,
        },
        'RORY: UDPv4 on 127.0.0.1 only': fast_rediscovery_env(
            {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}),
    }


def measure(extra: dict[str, str], runs: int, peers: int, domain: int) -> list[float]:
    """Milliseconds from publish to receipt for ``runs`` restarts under one setting."""
    env = {k: v for k, v in os.environ.items() if not k.startswith('FAST')}
    env.update({'ROS_DOMAIN_ID': str(domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'})
    env.update(extra)  # may replace the range (RORY's localhost profile)
    procs: list[subprocess.Popen[Any]] = []
    try:
        listener = subprocess.Popen(
            [sys.executable, '-c', LISTENER], env=env, stdout=subprocess.PIPE, text=True
        )
        procs.append(listener)
        for _ in range(peers):
            procs.append(subprocess.Popen([sys.executable, '-c', IDLE], env=env))
        assert listener.stdout is not None
        assert listener.stdout.readline().strip() == 'ready'
        time.sleep(2.0)
        delays: list[float] = []
        for _ in range(runs):
            child = subprocess.Popen([sys.executable, '-c', CHILD], env=env)
            line = listener.stdout.readline().split()
            sent, received = int(line[0]), int(line[1])
            delays.append((received - sent) / 1e6)
            child.kill()
            child.wait()
            time.sleep(float(os.environ.get("RORY_DISCOVERY_PAUSE", "0.5")))
        return delays
    finally:
        for proc in procs:
            proc.kill()
            proc.wait()


def main() -> None:
    """Run every setting and print a table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=10)
    parser.add_argument('--peers', type=int, default=4)
    parser.add_argument('--domain', type=int, default=97)
    args = parser.parse_args()
    print(f'{"DDS setting":32} {"median ms":>10} {"worst ms":>10}   ({args.runs} restarts, '
          f'{args.peers} idle peers)')
    for name, extra in _settings().items():
        delays = measure(extra, args.runs, args.peers, args.domain)
        print(f'{name:32} {statistics.median(delays):10.1f} {max(delays):10.1f}', flush=True)
        # Leftover shared-memory segments of killed children slow the next setting down.
        for leftover in Path('/dev/shm').glob('fastrtps_*'):
            leftover.unlink(missing_ok=True)


if __name__ == '__main__':
    main()
