"""What the node runtime adds per event, measured in-process: microseconds per message or tick.

    python -m rory_eval.bench.hot_path_bench [--events 20000] [--repeats 5]

``message_cost_bench`` measures a whole node under ``rory supervise``, executor and DDS
included, and on a shared VM its figures move by tens of microseconds from run to run. This
bench isolates the part RORY owns: the same loop of events through

* ``bare``: what rclpy does for a plain node (deserialise a LaserScan and call the callback;
  call a timer callback that reads the node's clock once);
* ``restart``: the runtime's path without a log (raw delivery, deserialising in Python, the
  in-flight slot, the lock, the output gate's state);
* ``rory``: that, and the write-ahead log (a message record; a tick record and a clock
  reading record), to segments on this machine's disk.

The subscription and timer are stand-ins holding what the runtime reads from rclpy's (the
executor's own work is the same in every configuration); the runtime, the message, the clock
and the log are the real ones. Configurations alternate; medians of ``--repeats``.
"""

from __future__ import annotations

import argparse
import array
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.clock import Clock, ROSClock
from rclpy.qos import QoSProfile
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import LaserScan

from rory_runtime.node.runtime import NodeRuntime, RuntimeEnv
from rory_runtime.node.state import CheckpointSpec
from rory_runtime.protocol import Method, Mode

CONFIGS = ('bare', 'restart', 'rory')


@dataclass
class _Subscription:
    """What NodeRuntime.adopt_subscription reads from an rclpy Subscription."""

    topic_name: str
    callback: Callable[..., Any]
    msg_type: type = LaserScan
    raw: bool = False
    qos_profile: QoSProfile = field(default_factory=lambda: QoSProfile(depth=1000))

    def get_publisher_count(self) -> int:
        return 1


@dataclass
class _Timer:
    """What NodeRuntime.adopt_timer and a tick read from an rclpy Timer."""

    callback: Callable[[], Any]
    clock: Clock
    canceled: bool = False

    def is_canceled(self) -> bool:
        return self.canceled

    def cancel(self) -> None:
        self.canceled = True

    def reset(self) -> None:
        self.canceled = False

    def destroy(self) -> None:
        self.canceled = True


def _scan() -> bytes:
    msg = LaserScan()
    msg.ranges = array.array('f', [1.0] * 360)
    msg.intensities = array.array('f', [0.5] * 360)
    msg.header.frame_id = 'laser'
    return bytes(serialize_message(msg))


class _Sink:
    """The node's callbacks: a count and the last stamp or clock time (scan_sink, tick_sink)."""

    def __init__(self) -> None:
        self.clock = ROSClock()
        self.count = 0
        self.last = 0

    def on_scan(self, msg: LaserScan) -> None:
        self.count += 1
        self.last = msg.header.stamp.sec

    def on_tick(self) -> None:
        self.count += 1
        self.last = self.clock.now().nanoseconds


def _runtime(config: str, store: Path) -> NodeRuntime:
    method = Method.RORY if config == 'rory' else Method.RESTART
    env = RuntimeEnv(node_id='bench', store=store, incarnation=1, method=method,
                     mode=Mode.FRESH, interval=2.0)
    runtime = NodeRuntime(CheckpointSpec(('count',), 'sha256:0'), env)
    return runtime


def _loop(config: str, kind: str, events: int, store: Path) -> float:
    """Seconds per event for one configuration."""
    sink = _Sink()
    raw = _scan()
    if config == 'bare':
        def step(n: int) -> None:
            if kind == 'message':
                sink.on_scan(deserialize_message(raw, LaserScan))
            else:
                sink.on_tick()
    else:
        runtime = _runtime(config, store)
        if kind == 'message':
            sub = _Subscription('/scan', sink.on_scan)
            runtime.adopt_subscription(sub)  # type: ignore[arg-type]
        else:
            timer = _Timer(sink.on_tick, sink.clock)
            runtime.adopt_timer(timer)  # type: ignore[arg-type]
        runtime.open_gates(next_segment=1)

        def step(n: int) -> None:
            if kind == 'message':
                sub.callback(raw, {'source_timestamp': n, 'received_timestamp': n,
                                   'publication_sequence_number': n,
                                   'reception_sequence_number': None})
            else:
                timer.callback()
    began = time.perf_counter()
    for n in range(1, events + 1):
        step(n)
    took = time.perf_counter() - began
    if config != 'bare':
        runtime.close()
    assert sink.count == events, f'{config} {kind}: {sink.count} of {events} applied'
    return took / events


def main(argv: Sequence[str] | None = None) -> int:
    """Run the bench; print the table."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.hot_path_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--events', type=int, default=20000)
    parser.add_argument('--repeats', type=int, default=5)
    args = parser.parse_args(argv)
    if args.events < 1 or args.repeats < 1:
        parser.error('--events and --repeats must be at least 1')
    results: dict[tuple[str, str], list[float]] = {}
    with tempfile.TemporaryDirectory(prefix='rory-hotpath-') as tmp:
        for repeat in range(args.repeats):
            order = CONFIGS if repeat % 2 == 0 else tuple(reversed(CONFIGS))
            for kind in ('message', 'tick'):
                for config in order:
                    store = Path(tmp) / f'{kind}-{config}-{repeat}'
                    results.setdefault((kind, config), []).append(
                        _loop(config, kind, args.events, store))
    print('| event | configuration | us per event | added to bare (us) |')
    print('|---|---|---:|---:|')
    for kind, what in (('message', 'LaserScan (360 beams)'), ('tick', 'timer tick, one clock '
                                                                      'reading')):
        bare = statistics.median(results[kind, 'bare']) * 1e6
        for config in CONFIGS:
            us = statistics.median(results[kind, config]) * 1e6
            added = '-' if config == 'bare' else f'{us - bare:+.1f}'
            print(f'| {what} | {config} | {us:.1f} | {added} |')
    print(f'\n{args.events} events per loop, medians of {args.repeats}.')
    return 0


if __name__ == '__main__':
    sys.exit(main())
