"""How long until a restarted process is heard: DDS rediscovery after SIGKILL.

    python -m rory_eval.bench.discovery [--runs 10] [--peers 4]

A long-lived listener (like the supervisor) holds a reliable transient-local subscription;
``--peers`` idle participants stand in for the rest of the robot. A child process starts,
publishes one message at once (like a node's HELLO) and is SIGKILLed once heard; this repeats.
Printed per DDS setting: median and worst time from the child's publish to the listener's
receipt, side by side in one run.

A SIGKILLed participant leaves its shared-memory files in /dev/shm, and leftovers slow the next
setting down; after each setting, the files this bench's own processes made are removed (read
from /proc/locks before they are killed, :func:`shm_files_of`) once no process holds them. Other
programs' files, live or left over, stay.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Collection, Iterable, Sequence
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


SHM = Path('/dev/shm')
LOCKS = Path('/proc/locks')


def shm_files_of(pids: Collection[int]) -> set[Path]:
    """Fast DDS's shared-memory files that processes ``pids`` hold: each segment or port in
    ``SHM`` whose lock file (``<name>_el``) one of them has locked (``flock``, as ``LOCKS``
    lists it), and that lock file. Read while they live: a SIGKILLed participant leaves its files
    behind, and then nothing says whose they were."""
    held: set[tuple[int, int, int]] = set()
    try:
        text = LOCKS.read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        # '1: FLOCK  ADVISORY  WRITE 4242 00:1b:152030 0 EOF' (a waiter's line: '1: -> FLOCK ...')
        fields = line.split()
        if len(fields) < 6 or fields[1] != 'FLOCK' or not fields[4].isdigit():
            continue
        if int(fields[4]) in pids:
            with contextlib.suppress(ValueError):
                major, minor, inode = fields[5].split(':')
                held.add((int(major, 16), int(minor, 16), int(inode)))
    files: set[Path] = set()
    for lock in SHM.glob('fastrtps_*_el'):
        try:
            stat = lock.stat()
        except OSError:
            continue
        if (os.major(stat.st_dev), os.minor(stat.st_dev), stat.st_ino) in held:
            files |= {lock, lock.with_name(lock.name.removesuffix('_el'))}
    return files


def remove_left_over(files: Iterable[Path]) -> list[Path]:
    """Remove those of ``files`` (:func:`shm_files_of`) that no process holds now: each lock file
    nobody has locked, and the segment or port it guards. One held again (a new participant took
    the name) stays. Returns what was removed."""
    removed: list[Path] = []
    for lock in sorted(f for f in files if f.name.endswith('_el')):
        try:
            fd = os.open(lock, os.O_RDONLY)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # as Fast DDS tells a dead owner
        except OSError:
            os.close(fd)
            continue
        try:
            for path in (lock.with_name(lock.name.removesuffix('_el')), lock):
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()
                    removed.append(path)
        finally:
            os.close(fd)
    return removed


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
    left: set[Path] = set()  # the shared-memory files of the processes killed so far
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
            procs.append(child)
            line = listener.stdout.readline().split()
            sent, received = int(line[0]), int(line[1])
            delays.append((received - sent) / 1e6)
            left |= shm_files_of({child.pid})
            child.kill()
            child.wait()
            procs.remove(child)
            time.sleep(float(os.environ.get("RORY_DISCOVERY_PAUSE", "0.5")))
        return delays
    finally:
        left |= shm_files_of({proc.pid for proc in procs})
        for proc in procs:
            proc.kill()
            proc.wait()
        # Leftover shared-memory segments of killed processes slow the next setting down.
        remove_left_over(left)


def main(argv: Sequence[str] | None = None) -> int:
    """Run every setting and print a table."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.discovery',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=10)
    parser.add_argument('--peers', type=int, default=4)
    parser.add_argument('--domain', type=int, default=97)
    args = parser.parse_args(argv)
    if args.runs < 1 or args.peers < 0:
        parser.error('--runs must be at least 1, --peers at least 0')
    print(f'{"DDS setting":32} {"median ms":>10} {"worst ms":>10}   ({args.runs} restarts, '
          f'{args.peers} idle peers)')
    for name, extra in _settings().items():
        delays = measure(extra, args.runs, args.peers, args.domain)
        print(f'{name:32} {statistics.median(delays):10.1f} {max(delays):10.1f}', flush=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
