"""What the supervisor's ring costs idle: its readers in a participant of their own, or in the
supervisor's.

Each run is a fresh process shaped like an idle supervisor: its node, spun by an executor, and
one passive ring reader per input topic (LaserScan, raw), made with
:class:`~rory_runtime.supervisor.ring.RingContext` either on a context of its own (``own``,
RORY before 2026-11-23) or on the supervisor's (``shared``). ``--peers`` idle participants on
the same domain stand in for the rest of the robot, which every participant must announce
itself to and track. The two configurations alternate run by run; the table gives medians of
the process's CPU (% of one core over ``--seconds``), its PSS and its thread count.

    python -m rory_eval.bench.ring_participant_bench --runs 5
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from collections.abc import Sequence

from rory_eval.harness.process_usage import read_process

CONFIGS = ('own', 'shared')


def _child(config: str, topics: int, seconds: float) -> None:
    """One idle supervisor-like process; prints its CPU, PSS and threads as JSON."""
    import rclpy
    import rclpy.utilities
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    from rory_runtime.protocol import InputSpec
    from rory_runtime.supervisor.ring import Ring, RingContext

    rclpy.init()
    sup = Node('rory_supervisor_bench')
    executor = SingleThreadedExecutor()
    executor.add_node(sup)
    ring_ctx = RingContext(sup.context if config == 'shared' else None)
    ring = Ring(ring_ctx, 'bench')
    ring.ensure(InputSpec(f'/bench_scan_{k}', 'sensor_msgs/msg/LaserScan', False, False, 10)
                for k in range(topics))
    time.sleep(2.0)  # discovery settles before measuring
    cpu_before = time.process_time()  # every thread of the process, DDS's included
    began = time.monotonic()
    while time.monotonic() - began < seconds:
        executor.spin_once(timeout_sec=0.5)
    cpu = 100.0 * (time.process_time() - cpu_before) / (time.monotonic() - began)
    reading = read_process(os.getpid(), with_pss=True)
    assert reading is not None
    threads = len(os.listdir(f'/proc/{os.getpid()}/task'))
    print(json.dumps({'cpu': cpu, 'pss_mb': reading.pss_mb, 'threads': threads}))
    ring_ctx.shutdown()
    executor.shutdown()
    rclpy.utilities.try_shutdown()


def _peers(count: int, env: dict[str, str]) -> subprocess.Popen[bytes] | None:
    if count == 0:
        return None
    code = ('import rclpy, time\nfrom rclpy.context import Context\nfrom rclpy.node import Node\n'
            f'ns = []\nfor k in range({count}):\n'
            '    c = Context(); rclpy.init(context=c); ns.append(Node(f"peer_{k}", context=c))\n'
            'time.sleep(3600)\n')
    return subprocess.Popen([sys.executable, '-c', code], env=env)


def main(argv: Sequence[str] | None = None) -> int:
    """Run both configurations ``--runs`` times, interleaved; print the medians."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.ring_participant_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--topics', type=int, default=3, help='ring readers (default 3)')
    parser.add_argument('--peers', type=int, default=4, help='other idle participants')
    parser.add_argument('--domain', type=int, default=77)
    parser.add_argument('--child', choices=CONFIGS, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        _child(args.child, args.topics, args.seconds)
        return 0
    if args.runs < 1 or args.seconds <= 0:
        parser.error('--runs must be at least 1 and --seconds positive')

    from rory_runtime.dds import fast_rediscovery_env

    env = {**os.environ, 'ROS_DOMAIN_ID': str(args.domain),
           'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    dds_env = {**env, **fast_rediscovery_env(env)}
    results: dict[str, list[dict[str, float]]] = {c: [] for c in CONFIGS}
    peers = _peers(args.peers, dds_env)
    try:
        for run in range(args.runs):
            for config in CONFIGS:
                out = subprocess.run(
                    [sys.executable, '-m', 'rory_eval.bench.ring_participant_bench', '--child',
                     config, '--topics', str(args.topics), '--seconds', str(args.seconds)],
                    env=dds_env, capture_output=True, text=True, check=True,
                    timeout=args.seconds + 60)
                results[config].append(json.loads(out.stdout.strip().splitlines()[-1]))
                print(f'run {run + 1} {config}: {results[config][-1]}', file=sys.stderr)
    finally:
        if peers is not None:
            # rclpy's signal handler may keep a sleeping process alive through SIGTERM (seen
            # with an idle test process): give it 5 s, then SIGKILL. Always reaped.
            peers.terminate()
            try:
                peers.wait(timeout=5)
            except subprocess.TimeoutExpired:
                peers.kill()
                peers.wait()
    print(f'| ring readers ({args.topics}) | CPU (% of a core) | PSS (MB) | threads |')
    print('|---|---:|---:|---:|')
    for config in CONFIGS:
        rows = results[config]
        label = ('a participant of their own' if config == 'own'
                 else "the supervisor's participant")
        print(f'| {label} | {statistics.median(r["cpu"] for r in rows):.2f} '
              f'| {statistics.median(r["pss_mb"] for r in rows):.1f} '
              f'| {statistics.median(r["threads"] for r in rows):.0f} |')
    return 0


if __name__ == '__main__':
    sys.exit(main())
