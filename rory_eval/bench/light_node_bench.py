"""What RORY costs on one light node: the example integrator at 50 Hz, bare against rory.

    python -m rory_eval.bench.light_node_bench [--runs 5] [--seconds 30] [--rate 50]

A user's light node is where RORY's fixed costs weigh most: a supervisor, a zygote and a standby
beside a node that takes a few percent of a core. Each run starts the integrator
(examples/integrator) as a user would, bare (``python integrator.py``, ROS's default DDS
settings) and under ``rory supervise`` with the defaults (method rory, warm standby, RORY's DDS
profile), with a publisher of 1, 2, 3, ... at ``--rate`` Hz; bare and rory alternate, the order
swapped from run to run, so that a drift in the machine's load touches both alike. After a
warm-up (every process up, the standby ready) the tree is measured over ``--seconds``: CPU in
percent of one core (its own time, the publisher's left out) and the sum of PSS at the end,
per role (node, supervisor, zygote, standby). Prints a Markdown table of medians and writes
``<out>/light_node.json``.
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
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from rory_eval.harness.process_usage import TreeSampler
from rory_eval.harness.scenario import EXAMPLE, prepare, stop_process
from rory_eval.harness.simrun import exit_on_sigterm
from rory_runtime.dds import fast_rediscovery_env

CONFIGS = ('bare', 'bare_udp', 'restart', 'checkpoint', 'replay', 'rory')
"""In the order they add mechanisms: ``bare_udp`` is the bare node under RORY's DDS profile
(UDPv4 on 127.0.0.1, no shared memory; rory_runtime/dds); ``restart`` the node under the
supervisor with nothing kept (the runtime's fixed cost); ``checkpoint`` adds checkpoints;
``replay`` logging and the ring, no checkpoints; ``rory`` all of it and the warm standby."""
WARM_UP = 10.0  # s: the node up, its first checkpoints, the standby forked and ready


def plain_env(domain: int) -> dict[str, str]:
    """What a user's shell gives a process: ROS's defaults, this run's domain."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(('FASTRTPS_', 'FASTDDS_'))}
    env['ROS_DOMAIN_ID'] = str(domain)
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['PYTHONUNBUFFERED'] = '1'
    return env


def run_once(config: str, workdir: Path, domain: int, seconds: float,
             rate: float) -> dict[str, Any]:
    """One configuration once; its tree's usage per role."""
    workdir.mkdir(parents=True, exist_ok=True)
    env = plain_env(domain)
    if config in ('bare', 'bare_udp'):
        command = [sys.executable, str(EXAMPLE / 'integrator.py')]
        readers = '1'
        if config == 'bare_udp':
            env.update(fast_rediscovery_env(env))
    else:
        supervise = prepare(workdir, config, interval=None, pace=None)
        command = [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(supervise)]
        readers = '2' if config in ('replay', 'rory') else '1'  # the ring reads too
    count = int(rate * (WARM_UP + seconds + 10.0))
    with (workdir / f'{config}.log').open('wb') as log:
        root = subprocess.Popen(command, env=env, cwd=workdir, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
        publisher = subprocess.Popen(
            [sys.executable, str(EXAMPLE / 'count_publisher.py'), str(count), str(rate),
             readers], env=env, cwd=workdir, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            time.sleep(WARM_UP)
            sampler = TreeSampler(root.pid)
            sampler.start()
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                time.sleep(1.0)
                sampler.sample()
            usage = sampler.finish()
            if publisher.poll() is not None:
                raise RuntimeError(f'{config}: the publisher ended early ({publisher.poll()})')
        finally:
            stop_process(publisher)
            stop_process(root)
    roles = {name: {'cpu_percent': round(100.0 * r.cpu_seconds / usage.wall_seconds, 2),
                    'pss_mb': round(r.pss_mb, 1), 'processes': r.processes,
                    # the second half's, per kind of thread (python, rory-io, dds.*)
                    'threads_percent': {
                        kind: round(100.0 * t / max(usage.steady_wall_seconds, 1e-9), 2)
                        for kind, t in r.steady_threads.items()}}
             for name, r in usage.roles.items() if name != 'reaped'}
    return {'config': config,
            'cpu_percent': round(100.0 * usage.cpu_seconds / usage.wall_seconds, 2),
            'pss_mb': round(usage.pss_mb, 1), 'roles': roles}


def summarise(runs: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Medians per configuration and of the per-repetition ratios to bare."""
    by = {c: [r for r in runs if r['config'] == c] for c in CONFIGS}
    pairs = list(zip(by['bare'], by['rory'], strict=False))
    out: dict[str, Any] = {}
    for config, group in by.items():
        if not group:
            continue
        roles = sorted({name for r in group for name in r['roles']})
        out[config] = {
            'cpu_percent': statistics.median(r['cpu_percent'] for r in group),
            'pss_mb': statistics.median(r['pss_mb'] for r in group),
            'roles': {name: {
                'cpu_percent': statistics.median(r['roles'].get(name, {}).get('cpu_percent', 0.0)
                                                 for r in group),
                'pss_mb': statistics.median(r['roles'].get(name, {}).get('pss_mb', 0.0)
                                            for r in group)} for name in roles},
        }
    if pairs:
        out['cpu_ratio'] = statistics.median(r['cpu_percent'] / b['cpu_percent']
                                             for b, r in pairs)
        out['pss_added_mb'] = statistics.median(r['pss_mb'] - b['pss_mb'] for b, r in pairs)
    return out


def table(summary: dict[str, Any], runs: int) -> str:
    """Markdown: per configuration and role, CPU and PSS (medians)."""
    lines = ['| configuration | role | CPU (% of a core) | PSS (MB) |', '|---|---|---:|---:|']
    for config in CONFIGS:
        if config not in summary:
            continue
        entry = summary[config]
        for role, usage in entry['roles'].items():
            lines.append(f'| {config} | {role} | {usage["cpu_percent"]:.2f} '
                         f'| {usage["pss_mb"]:.1f} |')
        lines.append(f'| {config} | **all** | **{entry["cpu_percent"]:.2f}** '
                     f'| **{entry["pss_mb"]:.1f}** |')
    if 'cpu_ratio' in summary:
        lines.append('')
        lines.append(f'rory against bare, medians of {runs} side-by-side pairs: CPU '
                     f'**{summary["cpu_ratio"]:.2f}x**, PSS **+{summary["pss_added_mb"]:.1f} MB**')
    return '\n'.join(lines)


def alternating(configs: Sequence[str], runs: int) -> Iterator[tuple[int, str]]:
    """(run, configuration) in the order the benches run them: every configuration once a run,
    the order reversed every other run, so that a drift in the machine's load touches them
    alike."""
    for i in range(runs):
        for config in (configs if i % 2 == 0 else list(reversed(configs))):
            yield i, config


def main(argv: Sequence[str] | None = None) -> int:
    """Run the bench; print the table."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.light_node_bench',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=5)
    parser.add_argument('--seconds', type=float, default=30.0, help='measured window (s)')
    parser.add_argument('--rate', type=float, default=50.0, help='numbers per second')
    parser.add_argument('--configs', nargs='+', choices=CONFIGS, default=['bare', 'rory'],
                        help='configurations to run (bare is needed for the ratios)')
    parser.add_argument('--domain', type=int, default=88)
    parser.add_argument('--out', help='keep the runs and light_node.json here')
    args = parser.parse_args(argv)
    if args.runs < 1 or args.seconds <= 0 or args.rate <= 0:
        parser.error('--runs must be at least 1, --seconds and --rate positive')
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-light-'))
    runs: list[dict[str, Any]] = []
    for i, config in alternating([c for c in CONFIGS if c in args.configs], args.runs):
        result = run_once(config, root / f'run{i}-{config}', args.domain, args.seconds,
                          args.rate)
        runs.append(result)
        print(f'[{i + 1}/{args.runs}] {config}: {result["cpu_percent"]:.2f} % of a core, '
              f'{result["pss_mb"]:.1f} MB PSS', flush=True)
    summary = summarise(runs)
    (root / 'light_node.json').write_text(json.dumps({'runs': runs, 'summary': summary},
                                                     indent=1))
    print()
    print(table(summary, args.runs))
    if not args.out:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
