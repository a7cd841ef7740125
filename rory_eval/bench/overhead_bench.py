"""Where RORY's overhead goes: its mechanisms switched on one at a time, beside the bare node.

    python -m rory_eval.bench.overhead_bench [--targets amcl grid_slam] [--world real_room]
                                       [--runs 3] [--out bench-out/overhead]

Each configuration runs the target's evaluation workload (the same simulator seed, route and
duration as ``rory eval``) with no crash:

- ``bare``: the original node, no RORY;
- ``restart``: the instrumented node under the supervisor with nothing kept: the runtime's
  fixed cost (raw delivery and deserialising, the heartbeat, status messages);
- ``checkpoint``: plus a checkpoint every 2 s;
- ``replay``: every input logged by the node and held by the supervisor's ring readers, no
  checkpoints;
- ``rory``: checkpoints and logging, plus the warm standby.

Within a repetition the configurations run one after the other, and repetitions repeat the
whole sequence, so that a drift in the machine's load touches every configuration alike. CPU is
the *steady* figure: the second half of the run, when every process is up, in % of one core
(one-time start-up costs, such as the standby's imports, are left out; the whole-run figure is
in ``overhead.json``). Memory is the sum over the processes of peak RSS (shared libraries
counted once per process) and of PSS at the end (shared pages split between their users).
Writes ``<out>/overhead.md`` and ``<out>/overhead.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import statistics
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rory_eval.harness.simrun import exit_on_sigterm
from rory_eval.runs.plan import BARE, WORLDS, RunSpec, duration_for
from rory_eval.runs.runner import RunRecord, execute, instrument
from rory_eval.targets import TARGETS

CONFIGS = (BARE, 'restart', 'checkpoint', 'replay', 'rory')
"""In the order they add mechanisms."""

ROLES = ('node', 'supervisor', 'zygote', 'standby')


def run_all(targets: Sequence[str], world: str, runs: int, out: Path, domain: int,
            *, configs: Sequence[str] = CONFIGS,
            progress: Any = print) -> dict[tuple[str, str], list[RunRecord]]:
    """Every target x configuration, ``runs`` times, interleaved; the records by cell."""
    records: dict[tuple[str, str], list[RunRecord]] = {}
    for target in targets:
        instrument(TARGETS[target], out / 'instrumented' / target)
    for repetition in range(runs):
        for target in targets:
            for config in configs:
                spec = RunSpec(target, world, config, repetition, None,
                               duration_for(target, world), seed=0)
                began = time.monotonic()
                folder = out / 'runs' / spec.name
                if folder.exists():
                    # A store left by an earlier bench would be recovered from.
                    shutil.rmtree(folder)
                record = execute(spec, folder, domain_id=domain,
                                 instrumented=out / 'instrumented' / target)
                records.setdefault((target, config), []).append(record)
                progress(f'[{repetition + 1}/{runs}] {target} {config}: '
                         f'{record.steady_cpu_percent:.1f}% steady'
                         f'{" ERROR " + record.error.splitlines()[0] if record.error else ""}'
                         f' ({time.monotonic() - began:.0f} s)')
    return records


def _median(values: Sequence[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return statistics.median(finite) if finite else math.nan


def _role(record: RunRecord, role: str, key: str) -> float:
    return float(record.usage_by_role.get(role, {}).get(key, 0.0))


def summarise(records: dict[tuple[str, str], list[RunRecord]]) -> list[dict[str, Any]]:
    """Per target and configuration: medians of the steady CPU per role and in all, and of
    the memory sums; runs that failed are left out and counted."""
    rows = []
    for target in TARGETS:
        bare_cpu = bare_pss = math.nan
        for config in CONFIGS:
            cell = records.get((target, config))
            if not cell:
                continue
            good = [r for r in cell if not r.error and r.usage_by_role]
            row: dict[str, Any] = {'target': target, 'config': config, 'runs': len(good),
                                   'failed': len(cell) - len(good)}
            for role in ROLES:
                row[role] = _median([_role(r, role, 'steady_cpu_percent') for r in good])
            row['all'] = _median([r.steady_cpu_percent for r in good])
            row['whole_run'] = _median([r.cpu_percent for r in good])
            row['peak_rss_mb'] = _median([r.peak_rss_mb for r in good])
            row['pss_mb'] = _median([r.pss_mb for r in good])
            if config == BARE:
                bare_cpu, bare_pss = row['all'], row['pss_mb']
            row['ratio'] = row['all'] / bare_cpu if bare_cpu else math.nan
            row['added_pss_mb'] = row['pss_mb'] - bare_pss
            rows.append(row)
    return rows


def table(rows: Sequence[dict[str, Any]]) -> str:
    """The Markdown table of :func:`summarise`'s rows."""
    lines = ['| program | configuration | runs | node | supervisor | zygote | standby | all '
             '| vs bare | whole run | peak RSS | PSS | PSS added |',
             '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|']

    def pct(v: float) -> str:
        return '-' if math.isnan(v) else f'{v:.1f}%'

    for row in rows:
        runs = f'{row["runs"]}' + (f' ({row["failed"]} failed)' if row['failed'] else '')
        roles = ' | '.join(pct(row[role]) if row['config'] != BARE or role == 'node' else '-'
                           for role in ROLES)
        added = '-' if row['config'] == BARE else f'{row["added_pss_mb"]:+.0f} MB'
        lines.append(f'| {row["target"]} | {row["config"]} | {runs} | {roles} | '
                     f'{pct(row["all"])} | {row["ratio"]:.2f}x | {pct(row["whole_run"])} | '
                     f'{row["peak_rss_mb"]:.0f} MB | {row["pss_mb"]:.0f} MB | {added} |')
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run, print and write the table."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.overhead_bench',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--targets', nargs='+', default=['amcl', 'grid_slam'],
                        choices=sorted(TARGETS))
    parser.add_argument('--world', default='real_room', choices=WORLDS)
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--domain', type=int, default=78, help='ROS_DOMAIN_ID of the runs')
    parser.add_argument('--out', type=Path, default=Path('bench-out/overhead'))
    parser.add_argument('--configs', nargs='+', default=list(CONFIGS), choices=CONFIGS,
                        help=f'configurations to run (default: all; ratios need {BARE})')
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error('--runs must be at least 1')
    if BARE not in args.configs:
        parser.error(f'--configs must include {BARE}: every ratio is to it')
    out = args.out.resolve()
    started = time.monotonic()
    configs = [c for c in CONFIGS if c in args.configs]
    records = run_all(args.targets, args.world, args.runs, out, args.domain, configs=configs)
    rows = summarise(records)
    text = (f'Steady CPU (% of one core, median of {args.runs}), world {args.world}, '
            f'{(time.monotonic() - started) / 60:.1f} min:\n\n{table(rows)}\n')
    print(text)
    (out / 'overhead.md').write_text(text)
    (out / 'overhead.json').write_text(json.dumps(
        {'rows': rows, 'records': {f'{t}/{c}': [r.usage_by_role for r in recs]
                                   for (t, c), recs in records.items()}}, indent=1) + '\n')
    return 0 if all(row['failed'] == 0 for row in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
