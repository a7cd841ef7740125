"""What RORY adds to taking one message, or one timer tick: microseconds of the node's CPU.

    python -m rory_eval.bench.message_cost_bench [--runs 3] [--rate 1000] [--seconds 10]
    python -m rory_eval.bench.message_cost_bench --input tick [--runs 3] [--seconds 10]

A node that does almost nothing per message (``examples/scan_sink``: a count and a stamp)
takes LaserScans (360 beams with intensities) at ``--rate`` Hz for ``--seconds`` s, bare and
under RORY's DDS profile (``bare_udp``: UDPv4 on 127.0.0.1, no shared memory; the profile every
process under RORY gets) and under ``rory supervise`` in two configurations: ``restart`` (the
runtime's fixed path: raw delivery, deserialising in Python, the in-flight slot, the output
gate) and ``rory`` (that, and the write-ahead log, checkpoints and the supervisor's ring; a
warm standby). The node
process's own CPU time over the publishing window, divided by the messages it took, is its
cost per message; the difference to bare is RORY's. At a rate this high the per-message cost
outweighs the fixed ones (the heartbeat's 5 wake-ups a second, a checkpoint every 2 s).
Configurations alternate, the order swapped from run to run. Prints a Markdown table, then
the same cost split by the node's threads (``schedstat``'s nanoseconds per thread: ``main`` is
the executor's thread, ``dds.udp`` Fast DDS's receive threads, ``rory-io`` the log's and
checkpoints' I/O), which says where the extra is spent.

With ``--input tick`` the node is ``examples/tick_sink`` instead: a 500 Hz timer whose callback
reads the node's clock once (as a node computing ``dt`` does) and counts, with no publisher;
under ``rory`` each tick and its clock reading are two records written ahead of the callback
(docs/architecture.md, "Timers and the clock"). The window starts 3 s after the node does,
and the ticks in it are its length times 500.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rory_eval.bench.light_node_bench import alternating, plain_env
from rory_eval.bench.rest_bench import Threads, per_kind, thread_ns
from rory_eval.harness.process_usage import read_process, tree_pids
from rory_eval.harness.scenario import Program, prepare, stop_process
from rory_eval.harness.simrun import exit_on_sigterm
from rory_runtime.dds import fast_rediscovery_env

REPO = Path(__file__).resolve().parents[2]
SINK = REPO / 'examples' / 'scan_sink'
TICKS = REPO / 'examples' / 'tick_sink'
PROGRAMS = {
    'scan': Program(SINK, SINK / 'keyvars.yaml', 'scan_sink.py', '/unused', 'scan_sink'),
    'tick': Program(TICKS, TICKS / 'keyvars.yaml', 'tick_sink.py', '/unused', 'tick_sink'),
}
TICK_RATE = 500.0  # examples/tick_sink's timer
CONFIGS = ('bare', 'bare_udp', 'restart', 'rory')
_TICK = float(os.sysconf('SC_CLK_TCK'))

PUBLISHER = r'''
import signal, sys, time, array, rclpy
signal.signal(signal.SIGINT, signal.SIG_DFL)  # stopped when done: no traceback in the output
from rclpy.qos import QoSProfile
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import LaserScan
count, rate, readers = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
node = rclpy.create_node('scan_source')
pub = node.create_publisher(LaserScan, '/scan', QoSProfile(depth=1000))
msg = LaserScan()
msg.ranges = array.array('f', [1.0] * 360)
msg.intensities = array.array('f', [0.5] * 360)
msg.header.frame_id = 'laser'
while pub.get_subscription_count() < readers:
    time.sleep(0.01)
time.sleep(1.0)
print('start', flush=True)
start = time.monotonic()
for i in range(count):
    delay = start + i / rate - time.monotonic()
    if delay > 0:
        time.sleep(delay)
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(i + 1, 1_000_000_000)
    pub.publish(msg)
pub.wait_for_all_acked(rclpy.duration.Duration(seconds=10.0))
print('end', flush=True)
'''


def _node_pid(root: int, config: str, deadline: float, program: Program, *,
              proc: Path = Path('/proc')) -> int:
    """The node's process: the root when bare, else the process of the supervisor's tree (root)
    running it. Not any process running it: another bench's node on the same machine has the
    same command line."""
    if config in ('bare', 'bare_udp'):
        return root
    while time.monotonic() < deadline:
        for pid in tree_pids(root, proc=proc):
            try:
                cmdline = (proc / str(pid) / 'cmdline').read_bytes().replace(b'\0', b' ')
            except OSError:
                continue
            if f'out/{program.file}'.encode() in cmdline:
                return pid
        time.sleep(0.1)
    raise RuntimeError(f'{config}: the node never started')


def run_ticks(config: str, workdir: Path, domain: int, seconds: float) -> dict[str, Any]:
    """One configuration once, ``--input tick``: the node's CPU per timer tick."""
    workdir.mkdir(parents=True, exist_ok=True)
    program = PROGRAMS['tick']
    with (workdir / f'{config}.log').open('wb') as log:
        root = subprocess.Popen(_command(config, workdir, program), env=_node_env(config, domain),
                                cwd=workdir, stdout=log, stderr=subprocess.STDOUT,
                                start_new_session=True)
        try:
            node = _node_pid(root.pid, config, time.monotonic() + 60, program)
            time.sleep(3.0)  # started, released, past its first checkpoint
            before, threads_before = read_process(node), thread_ns(node)
            started = time.monotonic()
            time.sleep(seconds)
            wall = time.monotonic() - started
            after, threads_after = read_process(node), thread_ns(node)
            if before is None or after is None:
                raise RuntimeError(f'{config}: the node ended')
        finally:
            stop_process(root)
    cpu = (after.own_ticks - before.own_ticks) / _TICK
    ticks = TICK_RATE * wall
    return {'config': config, 'messages': ticks, 'cpu_s': cpu, 'wall_s': wall,
            'us_per_message': 1e6 * cpu / ticks,
            'threads_us': thread_us(threads_before, threads_after, node, ticks)}


def thread_us(before: Threads, after: Threads, node: int, messages: float) -> dict[str, float]:
    """Microseconds of CPU per message for each kind of thread of process ``node`` between two
    ``thread_ns`` readings; its main thread (the executor's, here) is ``main``."""
    def relabel(threads: Threads) -> Threads:
        return {tid: ('main' if tid == node else kind, ns, runs)
                for tid, (kind, ns, runs) in threads.items()}

    grown = per_kind(relabel(before), relabel(after))
    return {kind: round(ns / 1e3 / messages, 2) for kind, ns in sorted(grown.items())}


def _node_env(config: str, domain: int) -> dict[str, str]:
    """The node's environment: a user's shell, with RORY's DDS profile for ``bare_udp`` (the
    supervisor gives it to its tree itself)."""
    env = plain_env(domain)
    if config == 'bare_udp':
        env.update(fast_rediscovery_env(env))
    return env


def _command(config: str, workdir: Path, program: Program) -> list[str]:
    if config in ('bare', 'bare_udp'):
        return [sys.executable, str(program.source / program.file)]
    supervise = prepare(workdir, config, interval=None, pace=None, program=program)
    return [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(supervise)]


def run_once(config: str, workdir: Path, domain: int, rate: float,
             seconds: float) -> dict[str, Any]:
    """One configuration once: the node's CPU per message."""
    workdir.mkdir(parents=True, exist_ok=True)
    env = plain_env(domain)
    program = PROGRAMS['scan']
    command = _command(config, workdir, program)
    readers = '2' if config == 'rory' else '1'  # the ring reads too
    count = int(rate * seconds)
    with (workdir / f'{config}.log').open('wb') as log:
        root = subprocess.Popen(command, env=_node_env(config, domain), cwd=workdir,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        publisher = subprocess.Popen([sys.executable, '-c', PUBLISHER, str(count), str(rate),
                                      readers], env=env, cwd=workdir, stdout=subprocess.PIPE,
                                     text=True, start_new_session=True)
        try:
            node = _node_pid(root.pid, config, time.monotonic() + 60, program)
            assert publisher.stdout is not None
            if publisher.stdout.readline().strip() != 'start':
                raise RuntimeError(f'{config}: the publisher never started')
            before, threads_before = read_process(node), thread_ns(node)
            started = time.monotonic()
            if publisher.stdout.readline().strip() != 'end':
                raise RuntimeError(f'{config}: the publisher did not finish')
            wall = time.monotonic() - started
            after, threads_after = read_process(node), thread_ns(node)
            if before is None or after is None:
                raise RuntimeError(f'{config}: the node ended')
        finally:
            stop_process(publisher)
            stop_process(root)
    cpu = (after.own_ticks - before.own_ticks) / _TICK
    return {'config': config, 'messages': count, 'cpu_s': cpu, 'wall_s': wall,
            'us_per_message': 1e6 * cpu / count,
            'threads_us': thread_us(threads_before, threads_after, node, count)}


def thread_table(runs: Sequence[dict[str, Any]], unit: str) -> str:
    """Per thread kind and configuration, the median microseconds per ``unit`` (Markdown);
    kinds that take under 0.5 us in every configuration are left out."""
    configs = [c for c in CONFIGS if any(r['config'] == c for r in runs)]
    kinds = sorted({k for r in runs for k in r['threads_us']})
    medians = {c: {k: statistics.median(r['threads_us'].get(k, 0.0)
                                        for r in runs if r['config'] == c)
                   for k in kinds} for c in configs}
    shown = [k for k in kinds if any(medians[c][k] >= 0.5 for c in configs)]
    lines = [f'| thread | {" | ".join(configs)} |', '|---|' + '---:|' * len(configs)]
    for kind in sorted(shown, key=lambda k: -max(medians[c][k] for c in configs)):
        lines.append(f'| {kind} | ' + ' | '.join(f'{medians[c][kind]:.1f}' for c in configs)
                     + ' |')
    return f'Node CPU per {unit} by thread (us, medians; schedstat):\n\n' + '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the bench; print the table."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.message_cost_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--input', choices=('scan', 'tick'), default='scan',
                        help='what the node takes: LaserScans, or ticks of its own timer')
    parser.add_argument('--rate', type=float, default=1000.0, help='scans per second')
    parser.add_argument('--seconds', type=float, default=10.0)
    parser.add_argument('--configs', default=','.join(CONFIGS),
                        help=f'which of {",".join(CONFIGS)} to run (comma-separated)')
    parser.add_argument('--domain', type=int, default=86)
    parser.add_argument('--out', help='keep the runs and message_cost.json here')
    args = parser.parse_args(argv)
    if args.runs < 1 or args.rate <= 0 or args.seconds <= 0:
        parser.error('--runs must be at least 1, --rate and --seconds positive')
    configs = [c for c in CONFIGS if c in args.configs.split(',')]
    if not configs or any(c not in CONFIGS for c in args.configs.split(',')):
        parser.error(f'--configs: a comma-separated choice of {",".join(CONFIGS)}')
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-msgcost-'))
    runs: list[dict[str, Any]] = []
    unit = 'tick' if args.input == 'tick' else 'message'
    for i, config in alternating(configs, args.runs):
        workdir = root / f'run{i}-{config}'
        result = (run_ticks(config, workdir, args.domain, args.seconds) if args.input == 'tick'
                  else run_once(config, workdir, args.domain, args.rate, args.seconds))
        runs.append(result)
        print(f'[{i + 1}/{args.runs}] {config}: {result["us_per_message"]:.1f} us a {unit}',
              flush=True)
    medians = {c: statistics.median(r['us_per_message'] for r in runs if r['config'] == c)
               for c in configs}
    (root / 'message_cost.json').write_text(json.dumps({'runs': runs, 'medians': medians},
                                                       indent=1))
    print()
    what = 'timer tick (one clock reading)' if args.input == 'tick' else 'LaserScan'
    print(f'| configuration | node CPU per {what} (us) | added to {configs[0]} (us) |')
    print('|---|---:|---:|')
    base = configs[0]  # bare, unless left out
    for config in configs:
        added = '-' if config == base else f'{medians[config] - medians[base]:+.1f}'
        print(f'| {config} | {medians[config]:.1f} | {added} |')
    print()
    print(thread_table(runs, unit))
    rate = TICK_RATE if args.input == 'tick' else args.rate
    print(f'\n{rate:g} Hz for {args.seconds:g} s, medians of {args.runs} runs.')
    if not args.out:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
