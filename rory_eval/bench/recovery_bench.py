"""``make bench``: recovery time per method, side by side, median of N runs.

    python -m rory_eval.bench.recovery_bench [--runs 10] [--kill-at 3.0] [--out bench-out]
        [--only rory-fast-cold rory-fast-warm ...]

Each run is the integrator scenario (300 numbers at 50 Hz, checkpoint every 2 s) SIGKILLed
``--kill-at`` seconds in; methods are interleaved run by run so that machine load affects them
alike. Recovery time is the supervisor's own measure, crash detected -> released (S4 done),
with its breakdown: restart (spawn -> the new process says HELLO, minus its restore), restore,
sync (the shadow path proven), replay (streaming until RELEASE).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

from rory_eval.harness.scenario import Kill, ScenarioResult, run
from rory_eval.harness.simrun import exit_on_sigterm

Config = tuple[str, str, bool]
"""(method, replay pace, warm standby)."""

# restart, checkpoint and replay as the paper ran them (cold starts); rory step by step: the
# paper's paced replay, then fast replay, then the warm standby, so each means shows its share.
CONFIGS: tuple[Config, ...] = (
    ('restart', 'paced', False),
    ('checkpoint', 'paced', False),
    ('replay', 'paced', False),
    ('rory', 'paced', False),
    ('rory', 'fast', False),
    ('rory', 'paced', True),
    ('rory', 'fast', True),
)
STEPS = ('restart_ms', 'restore_ms', 'sync_ms', 'replay_ms')


def _name(config: Config) -> str:
    method, pace, warm = config
    return f'{method}-{pace}-{"warm" if warm else "cold"}'


def _median(values: list[float]) -> str:
    return f'{statistics.median(values):.0f}' if values else '-'


def report(results: dict[Config, list[ScenarioResult]]) -> str:
    """Markdown table of medians per configuration."""
    lines = [
        '| method | replay | start | runs correct | recovery median (ms) | min | max | '
        + ' | '.join(s.removesuffix('_ms') for s in STEPS)
        + ' |',
        '|---|---|---|---:|---:|---:|---:|' + '---:|' * len(STEPS),
    ]
    for (method, pace, warm), runs in results.items():
        recoveries = [r.recoveries[0] for r in runs if r.recoveries]
        totals = [float(e['total_ms']) for e in recoveries]
        steps = [_median([float(e[s]) for e in recoveries]) for s in STEPS]
        correct = sum(r.correct for r in runs)
        lines.append(
            f'| {method} | {pace if method in ("rory", "replay") else "-"} | '
            f'{"warm standby" if warm else "cold"} | '
            f'{correct}/{len(runs)} | {_median(totals)} | '
            f'{min(totals, default=0):.0f} | {max(totals, default=0):.0f} | '
            + ' | '.join(steps)
            + ' |'
        )
    return '\n'.join(lines)


def main() -> None:
    """Run the benchmark."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', type=int, default=10)
    parser.add_argument('--kill-at', type=float, default=3.0)
    parser.add_argument('--out', type=Path, default=Path('bench-out'))
    parser.add_argument('--only', nargs='+', metavar='METHOD-PACE-START', choices=[
        _name(c) for c in CONFIGS], help='these configurations alone (e.g. rory-fast-cold)')
    args = parser.parse_args()
    domain = int(os.environ.get('ROS_DOMAIN_ID', '78'))
    configs = [c for c in CONFIGS if args.only is None or _name(c) in args.only]
    results: dict[Config, list[ScenarioResult]] = {c: [] for c in configs}
    began = time.monotonic()
    for i in range(args.runs):
        for method, pace, warm in configs:
            result = run(
                method, (Kill(after=args.kill_at),),
                args.out / f'{method}-{pace}-{"warm" if warm else "cold"}',
                domain_id=domain, pace=pace, warm_standby=warm,
            )
            results[(method, pace, warm)].append(result)
            total = result.recovery_ms[0] if result.recovery_ms else float('nan')
            print(
                f'run {i + 1}/{args.runs} {method:10} {pace:5} {"warm" if warm else "cold"} '
                f'recovered in {total:7.0f} ms, '
                f'correct={result.correct}',
                flush=True,
            )
    text = report(results)
    minutes = (time.monotonic() - began) / 60
    print(f'\nSIGKILL {args.kill_at:g} s in, {args.runs} runs per method ({minutes:.1f} min)\n')
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / 'recovery.md').write_text(text + '\n')


if __name__ == '__main__':
    main()
