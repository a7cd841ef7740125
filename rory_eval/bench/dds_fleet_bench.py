"""What DDS discovery settings cost a robot at rest, and what they buy after a crash.

    python -m rory_eval.bench.dds_fleet_bench [--participants 20] [--seconds 20] [--restarts 8]

RORY's DDS profile (rory_runtime/dds/) announces every participant every 0.25 s with a 1 s
lease, so that a SIGKILLed process is forgotten within 1 s. Every participant pays for every
other one's announcements, so that work grows with the graph: on a robot of 20 participants
(10 nodes under RORY and their peers) it is paid 20 times over, at rest. This bench measures,
for each setting side by side in one run:

* **at rest**: ``--participants`` idle rclpy processes (``rclpy.init`` and one node; nothing
  published), after a settle of ``--settle`` s, CPU per process over ``--seconds`` s;
* **after a crash**: a listener and four idle peers; a process starts, publishes one message
  and is SIGKILLed once heard, ``--restarts`` times: the time from its publish to the
  listener's receipt (a cold restart: a new participant; a warm standby's is known already).

Settings: Fast DDS's defaults (lease 20 s, announced every 3 s), RORY's profile, its node
variant (the one node processes run: builtin writers asynchronous), and RORY's profile with
other leases and announcement periods (``--leases``): same transport, same initial
announcements. All under
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` as RORY runs it (UDPv4 on 127.0.0.1, 64 initial
peer ports). Prints a Markdown table and writes ``<out>/dds_fleet.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rory_eval.bench.discovery import measure, remove_left_over, shm_files_of
from rory_eval.harness.simrun import exit_on_sigterm
from rory_runtime.dds import fast_rediscovery_env, node_profile_env

IDLE = r'''
import os, rclpy
rclpy.init()
n = rclpy.create_node('fleet_%d' % os.getpid())
rclpy.spin(n)
'''


def profiles(folder: Path, leases: Sequence[tuple[float, float]]) -> dict[str, dict[str, str]]:
    """Each setting's environment (profile files written to ``folder``): RORY's, and RORY's
    with each (lease, announcement period) of ``leases``."""
    rory = fast_rediscovery_env({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'})
    template = Path(rory['FASTRTPS_DEFAULT_PROFILES_FILE']).read_text()
    # What node processes and standbys run (rory_runtime/dds/fast_rediscovery*_node.xml).
    settings: dict[str, dict[str, str]] = {'RORY\'s profile': rory,
                                           'RORY\'s node profile': {**rory,
                                                                    **node_profile_env(rory)}}
    for lease, every in leases:
        whole, part = int(lease), round((lease % 1) * 1e9)
        text = re.sub(r'<leaseDuration>.*?</leaseDuration>',
                      f'<leaseDuration><sec>{whole}</sec><nanosec>{part}</nanosec>'
                      '</leaseDuration>', template)
        seconds, nanos = int(every), round((every % 1) * 1e9)
        text = re.sub(r'<leaseAnnouncement>.*?</leaseAnnouncement>',
                      f'<leaseAnnouncement><sec>{seconds}</sec><nanosec>{nanos}</nanosec>'
                      '</leaseAnnouncement>', text)
        path = folder / f'lease_{lease:g}s_{every:g}s.xml'
        path.write_text(text)
        settings[f'lease {lease:g} s, announced every {every:g} s'] = {
            **rory, 'FASTRTPS_DEFAULT_PROFILES_FILE': str(path)}
    return settings


def cpu_seconds(pid: int) -> float | None:
    """CPU time of every thread of ``pid`` so far, from each thread's ``schedstat`` (ns on the
    CPU; ``stat``'s 10 ms ticks are too coarse for an idle participant: one tick in 20 s is
    0.05 % of a core); None once the process is gone."""
    total = 0
    try:
        tasks = os.listdir(f'/proc/{pid}/task')
    except OSError:
        return None
    for task in tasks:
        try:
            total += int(Path(f'/proc/{pid}/task/{task}/schedstat').read_text().split()[0])
        except (OSError, ValueError, IndexError):
            continue  # a thread that ended meanwhile
    return total / 1e9


def at_rest(extra: dict[str, str], participants: int, settle: float, seconds: float,
            domain: int) -> list[float]:
    """CPU of each idle participant, in percent of a core."""
    env = {k: v for k, v in os.environ.items() if not k.startswith('FAST')}
    env.update({'ROS_DOMAIN_ID': str(domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'})
    env.update(extra)
    procs = [subprocess.Popen([sys.executable, '-c', IDLE], env=env, start_new_session=True)
             for _ in range(participants)]
    try:
        time.sleep(settle)
        before = {p.pid: cpu_seconds(p.pid) for p in procs}
        started = time.monotonic()
        time.sleep(seconds)
        after = {p.pid: cpu_seconds(p.pid) for p in procs}
        wall = time.monotonic() - started
        usage = []
        for pid, then in before.items():
            now = after.get(pid)
            if then is not None and now is not None:
                usage.append(100.0 * (now - then) / wall)
        return usage
    finally:
        left = shm_files_of({p.pid for p in procs})
        for proc in procs:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        # Their shared-memory files would slow the next setting down (those of no other process).
        remove_left_over(left)


def main(argv: Sequence[str] | None = None) -> int:
    """Measure every setting; print the table."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.dds_fleet_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--participants', type=int, default=20)
    parser.add_argument('--settle', type=float, default=12.0)
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--restarts', type=int, default=8)
    parser.add_argument('--leases', nargs='*', default=['3:1', '20:3'], metavar='LEASE:EVERY',
                        help="RORY's profile with these lease durations and announcement "
                             'periods (s) beside it')
    parser.add_argument('--domain', type=int, default=87)
    parser.add_argument('--out', help='write dds_fleet.json here')
    args = parser.parse_args(argv)
    if args.participants < 1 or args.restarts < 0:
        parser.error('--participants must be at least 1, --restarts at least 0')
    folder = Path(tempfile.mkdtemp(prefix='rory-dds-'))
    results: list[dict[str, Any]] = []
    try:
        try:
            leases = [tuple(float(x) for x in item.split(':')) for item in args.leases]
        except ValueError:
            parser.error('--leases takes LEASE:EVERY pairs in seconds, e.g. 3:1')
        if any(len(pair) != 2 or not 0 < pair[1] < pair[0] for pair in leases):
            parser.error('--leases: each LEASE:EVERY needs 0 < EVERY < LEASE')
        settings = {'Fast DDS defaults': {},
                    **profiles(folder, [(a, b) for a, b in leases])}
        for name, extra in settings.items():
            # Fast DDS's defaults under LOCALHOST: shared memory and UDPv4 (no profile).
            cpu = at_rest(extra, args.participants, args.settle, args.seconds, args.domain)
            delays = measure(extra, args.restarts, 4, args.domain) if args.restarts else []
            results.append({'setting': name, 'cpu_percent': cpu, 'restart_ms': delays})
            print(f'{name}: {statistics.median(cpu):.3f} % per participant at rest; restart '
                  f'heard after {statistics.median(delays) if delays else float("nan"):.0f} ms '
                  f'median, {max(delays) if delays else float("nan"):.0f} ms worst', flush=True)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    print()
    print(f'| setting | CPU per participant at rest, {args.participants} participants '
          f'(% of a core) | whole graph at rest | restart heard, median (ms) | worst (ms) |')
    print('|---|---:|---:|---:|---:|')
    for r in results:
        cpu = r['cpu_percent']
        delays = r['restart_ms']
        print(f'| {r["setting"]} | {statistics.median(cpu):.3f} | {sum(cpu):.2f} '
              f'| {statistics.median(delays) if delays else float("nan"):.0f} '
              f'| {max(delays) if delays else float("nan"):.0f} |')
    if args.out:
        Path(args.out).mkdir(parents=True, exist_ok=True)
        (Path(args.out) / 'dds_fleet.json').write_text(json.dumps(results, indent=1))
    return 0


if __name__ == '__main__':
    sys.exit(main())
