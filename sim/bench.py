"""CPU cost of the simulator: CPU seconds per simulated second, median of N runs.

``python -m sim.bench [--world office_small] [--runs 5] [--duration 30]``

Each run starts, in its own ROS domain (localhost only):
- ``--sinks N`` *sinks* (default 1): processes subscribed to every sensor topic (``/scan``,
  ``/camera/depth/points``, ``/camera/depth/camera_info``, ``/odom``, ``/ground_truth/pose``,
  ``/clock``), as the targets will be, so that the simulator pays for delivering to readers;
- the simulator, all sensors on, with the route driver as its own ROS node sending ``/cmd_vel``
  at 20 Hz (``sim run --driver route --duration D``).

The figure is the simulator process's own CPU time (all its threads, DDS included) over the
sim seconds of its real-time loop, as ``sim run`` reports it; start-up (imports, model compile,
map) is reported apart. The sink's and the driver's CPU are not counted.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

SINK_TOPICS = (
    ('/scan', 'sensor_msgs.msg', 'LaserScan'),
    ('/camera/depth/points', 'sensor_msgs.msg', 'PointCloud2'),
    ('/camera/depth/camera_info', 'sensor_msgs.msg', 'CameraInfo'),
    ('/odom', 'nav_msgs.msg', 'Odometry'),
    ('/ground_truth/pose', 'geometry_msgs.msg', 'PoseStamped'),
    ('/clock', 'rosgraph_msgs.msg', 'Clock'),
)


def _sink() -> int:
    """Subscribe to every sensor topic and count messages until SIGINT/SIGTERM."""
    import importlib

    import rclpy
    import rclpy.utilities
    from rclpy.executors import ExternalShutdownException

    from .qos import SENSOR_QOS

    rclpy.init()
    node = rclpy.create_node('bench_sink')
    counts: dict[str, int] = {}

    def counter(topic: str) -> Any:
        def on_msg(_msg: Any) -> None:
            counts[topic] = counts.get(topic, 0) + 1
        return on_msg

    for topic, module, name in SINK_TOPICS:
        msg_type = getattr(importlib.import_module(module), name)
        node.create_subscription(msg_type, topic, counter(topic), SENSOR_QOS)
    with contextlib.suppress(KeyboardInterrupt, ExternalShutdownException):
        rclpy.spin(node)
    print(json.dumps(counts), flush=True)
    node.destroy_node()
    rclpy.utilities.try_shutdown()
    return 0


def _env(domain: int) -> dict[str, str]:
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(domain)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    return env


def one_run(world: str, duration: float, domain: int, workdir: Path,
            driver: str = 'route', sinks: int = 1) -> dict[str, Any]:
    """One measured run; the simulator's summary plus its whole-process CPU."""
    env = _env(domain)
    readers = [
        subprocess.Popen([sys.executable, '-m', 'sim.bench', '--sink'], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        for _ in range(sinks)
    ]
    out = workdir / f'run_{domain}'
    try:
        time.sleep(1.0)  # the sinks' participants up before the simulator starts
        sim = subprocess.Popen(
            [sys.executable, '-m', 'sim', 'run', '--world', world, '--driver', driver,
             '--duration', str(duration), '--out', str(out),
             '--wait-for', f'/scan={sinks}'],
            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            _, status, usage = os.wait4(sim.pid, 0)
            sim.returncode = os.waitstatus_to_exitcode(status)
        finally:
            if sim.returncode is None:
                sim.kill()
                sim.wait()
    finally:
        outputs = []
        for reader in readers:
            reader.send_signal(2)
            try:
                outputs.append(reader.communicate(timeout=5)[0])
            except subprocess.TimeoutExpired:
                reader.kill()
                outputs.append(reader.communicate()[0])
        sink_out = outputs[0]
    summary: dict[str, Any] = json.loads((out / 'summary.json').read_text())
    summary['process_cpu_seconds'] = round(usage.ru_utime + usage.ru_stime, 3)
    summary['max_rss_mb'] = round(usage.ru_maxrss / 1024, 1)
    try:
        summary['sink_counts'] = json.loads(sink_out.decode().strip().splitlines()[-1])
    except (IndexError, ValueError):
        summary['sink_counts'] = {}
    return summary


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print one line per run, then the median."""
    parser = argparse.ArgumentParser(prog='python -m sim.bench', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--world', default='office_small')
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--duration', type=float, default=30.0, help='sim seconds per run')
    parser.add_argument('--driver', choices=('route', 'internal'), default='route')
    parser.add_argument('--sinks', type=int, default=1,
                        help='reader processes subscribed to every sensor topic (default 1)')
    parser.add_argument('--domain', type=int, default=180, help='first ROS domain id to use')
    parser.add_argument('--json', help='also write the results here')
    parser.add_argument('--sink', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.sink:
        return _sink()
    results = []
    with tempfile.TemporaryDirectory(prefix='sim-bench-') as tmp:
        for k in range(args.runs):
            r = one_run(args.world, args.duration, args.domain + k, Path(tmp), args.driver,
                        args.sinks)
            results.append(r)
            print(f'run {k + 1}: {r["cpu_per_sim_second"]:.4f} CPU s per sim s '
                  f'(loop {r["cpu_seconds"]:.2f} s CPU over {r["sim_seconds"]:.1f} sim s, '
                  f'whole process {r["process_cpu_seconds"]:.2f} s, RTF '
                  f'{r["real_time_factor"]:.3f}, scans delivered '
                  f'{r["sink_counts"].get("/scan", 0)}, clouds '
                  f'{r["sink_counts"].get("/camera/depth/points", 0)})', flush=True)
    per_s = [r['cpu_per_sim_second'] for r in results]
    median = statistics.median(per_s)
    print(f'{args.world}: median {median:.4f} CPU s per sim s ({100 * median:.1f}% of one core) '
          f'over {args.runs} runs of {args.duration:g} sim s, all sensors on, '
          f'{args.sinks} reader(s) of every sensor topic')
    if args.json:
        Path(args.json).write_text(json.dumps({'median': median, 'runs': results}, indent=2))
    return 0


if __name__ == '__main__':
    sys.exit(main())
