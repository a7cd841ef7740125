"""Checkpoint stall: how long a checkpoint holds the node's executor, by size of state.

    python -m rory_eval.bench.stall_bench [--sizes 1 16] [--seconds 12] [--out stall-out]

``examples/big_state`` (a node whose state is a float32 grid of the given size in MB, changed
by a 20 Hz timer) runs under ``rory supervise`` with a checkpoint every 0.5 s. The node's
runtime reports each checkpoint's *stall*: the time between two callbacks during which the
snapshot is taken under the callbacks' lock (read the variables, encode them). Writing,
fsync and pruning happen afterwards on a background thread and are reported as *total*.
Writes ``<out>/stall.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

from rory_eval.harness.scenario import Program, child_process, prepare, scenario_env

EXAMPLE = Path(__file__).resolve().parents[2] / 'examples' / 'big_state'


def measure(megabytes: float, seconds: float, out: Path, domain: int) -> list[dict[str, float]]:
    """The checkpoint events of one run with a state of ``megabytes``."""
    program = Program(EXAMPLE, EXAMPLE / 'keyvars.yaml', 'big_state.py', '/unused', 'big_state',
                      settings=(('env', {'BIG_STATE_MB': f'{megabytes:g}'}),))
    workdir = (out / f'{megabytes:g}MB').resolve()
    config = prepare(workdir, 'checkpoint', interval=0.5, pace=None, program=program)
    store = workdir / 'store-checkpoint'
    if store.exists():
        shutil.rmtree(store)
    with child_process([sys.executable, '-m', 'rory_runtime.cli',
                   'supervise', str(config)], scenario_env(domain), workdir,
                  workdir / 'supervisor.log'):
        time.sleep(seconds)
    events = [json.loads(line) for line in (store / 'events.jsonl').read_text().splitlines()]
    return [e for e in events if e.get('kind') == 'checkpoint']


def main() -> int:
    """Measure every size; print and write the table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--sizes', type=float, nargs='+', default=[1.0, 16.0], help='MB')
    parser.add_argument('--seconds', type=float, default=12.0)
    parser.add_argument('--out', type=Path, default=Path('stall-out'))
    args = parser.parse_args()
    domain = int(os.environ.get('ROS_DOMAIN_ID', '79'))
    lines = ['| state | checkpoints | encoded size | stall median (ms) | p90 | max | '
             'total median (ms) |', '|---:|---:|---:|---:|---:|---:|---:|']
    for size in args.sizes:
        events = measure(size, args.seconds, args.out, domain)
        if not events:
            lines.append(f'| {size:g} MB | 0 | - | - | - | - | - |')
            continue
        stalls = sorted(float(e['stall_ms']) for e in events)
        totals = [float(e['total_ms']) for e in events]
        p90 = stalls[min(len(stalls) - 1, int(0.9 * len(stalls)))]
        lines.append(
            f'| {size:g} MB | {len(events)} | {max(int(e["bytes"]) for e in events) / 1e6:.1f} MB'
            f' | {statistics.median(stalls):.2f} | {p90:.2f} | {stalls[-1]:.2f} | '
            f'{statistics.median(totals):.1f} |'
        )
    text = '\n'.join(lines)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'stall.md').write_text(text + '\n')
    print(text)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
