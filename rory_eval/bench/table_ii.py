"""The paper's Table II on a quiet machine: each target bare and under RORY, and the six targets
under one supervisor.

    python -m rory_eval.bench.table_ii [--targets ...] [--runs 3] [--stack-runs 3]
                                       [--world real_room] [--domain 88] [--out bench-out/table-ii]
    python -m rory_eval.bench.table_ii --report DIR [DIR ...]

Each target runs its evaluation workload (``rory eval``'s seed, route and duration), with no
crash: bare (the original node) and under RORY (method rory: checkpoints, the write-ahead log,
the supervisor's ring and the warm standby), one after the other, the order reversed from
repetition to repetition. The stack row is :mod:`rory_eval.bench.stack_bench`'s ``bare`` and
``rory`` configurations: the six targets as six processes against the six under one supervisor.

Measured as docs/performance.md measures, not as ``rory eval`` does under its load: CPU is the
process tree's *steady* figure (the second half of the run, every process up) in % of one core,
memory its PSS at the end (a shared library split between the processes that map it), the
simulator left out. The ratio and the PSS added are medians over the repetitions of each
pair (the RORY run against the bare run of the same repetition). The machine's load average is
written before and after, so that a reader can tell the sitting was quiet.

Writes ``<out>/table_ii.json`` and ``<out>/table_ii.md``. A sitting may run some of the targets
(``--targets``) and leave the stack out (``--stack-runs 0``); ``--report`` puts the folders of
several sittings into one table.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import shutil
import statistics
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from rory_eval.bench.light_node_bench import alternating
from rory_eval.runs.plan import BARE, WORLDS, RunSpec, duration_for
from rory_eval.targets import TARGETS

STACK = 'stack'
"""The stack row's program name: the six targets under one supervisor."""
CONFIGS = (BARE, 'rory')
RESULT = 'table_ii.json'


@dataclass(frozen=True)
class Pair:
    """One repetition: the bare run and the RORY run beside it (CPU in % of a core, PSS in MB)."""

    bare_cpu: float
    bare_pss: float
    rory_cpu: float
    rory_pss: float
    rory_own_cpu: float  # of rory_cpu, all but the node: the supervisor, zygote and standby


@dataclass(frozen=True)
class Row:
    """A program's line of Table II: medians over its pairs."""

    program: str
    pairs: int
    failed: int
    bare_cpu: float
    bare_pss: float
    rory_cpu: float
    rory_pss: float
    rory_own_cpu: float
    cpu_ratio: float
    pss_added: float
    # The node's own processes under RORY against the bare run (issue 36's figure): median of
    # each pair's (rory_cpu - rory_own_cpu) / bare_cpu; NaN in sittings from before it.
    node_ratio: float = float('nan')


class TableIIError(Exception):
    """A sitting's folder that cannot be read; the message names it."""


def row(program: str, pairs: Sequence[Pair], failed: int = 0) -> Row:
    """Medians of each figure over the pairs, and of each pair's ratio and PSS added."""
    def median(values: Iterable[float]) -> float:
        return statistics.median(values) if pairs else float('nan')

    return Row(program, len(pairs), failed,
               median(p.bare_cpu for p in pairs), median(p.bare_pss for p in pairs),
               median(p.rory_cpu for p in pairs), median(p.rory_pss for p in pairs),
               median(p.rory_own_cpu for p in pairs),
               median(p.rory_cpu / p.bare_cpu for p in pairs),
               median(p.rory_pss - p.bare_pss for p in pairs),
               median((p.rory_cpu - p.rory_own_cpu) / p.bare_cpu for p in pairs))


def table(rows: Sequence[Row]) -> str:
    """Markdown, one line per program, the stack last."""
    lines = ['| program | pairs | original CPU | original PSS | RORY CPU | RORY PSS '
             '| of which RORY\'s processes | the node\'s own process(es) against bare |',
             '|---|---:|---:|---:|---:|---:|---:|---:|']
    for r in sorted(rows, key=lambda r: (r.program == STACK, _order(r.program))):
        name = 'the six, one supervisor' if r.program == STACK else r.program
        pairs = f'{r.pairs}' + (f' ({r.failed} failed)' if r.failed else '')
        if not r.pairs:
            lines.append(f'| {name} | {pairs} | - | - | - | - | - | - |')
            continue
        lines.append(f'| {name} | {pairs} | {r.bare_cpu:.1f}% | {r.bare_pss:.0f} MB '
                     f'| {r.rory_cpu:.1f}% ({r.cpu_ratio:.2f}x) '
                     f'| {r.rory_pss:.0f} MB ({r.pss_added:+.0f} MB) | {r.rory_own_cpu:.1f}% '
                     f'| {_ratio(r.node_ratio)} |')
    return '\n'.join(lines)


def _ratio(value: float) -> str:
    return '-' if math.isnan(value) else f'{value:.2f}x'


def _order(program: str) -> int:
    names = list(TARGETS)
    return names.index(program) if program in names else len(names)


def target_pairs(target: str, world: str, runs: int, out: Path, domain: int,
                 progress: Callable[[str], None] = print) -> tuple[list[Pair], int]:
    """The target's evaluation workload bare and under RORY, ``runs`` times alternating."""
    from rory_eval.runs.runner import RunRecord, execute, instrument

    instrumented = instrument(TARGETS[target], out / 'instrumented' / target)
    records: dict[int, dict[str, RunRecord]] = {}
    for repetition, config in alternating(CONFIGS, runs):
        spec = RunSpec(target, world, config, repetition, None, duration_for(target, world),
                       seed=0)
        folder = out / 'runs' / spec.name
        if folder.exists():
            # A store left by an earlier sitting would be recovered from.
            shutil.rmtree(folder)
        began = time.monotonic()
        record = execute(spec, folder, domain_id=domain, instrumented=instrumented)
        records.setdefault(repetition, {})[config] = record
        error = f' ERROR {record.error.splitlines()[0]}' if record.error else ''
        progress(f'[{repetition + 1}/{runs}] {target} {config}: '
                 f'{record.steady_cpu_percent:.1f}% steady, {record.pss_mb:.0f} MB PSS{error} '
                 f'({time.monotonic() - began:.0f} s)')
    pairs = []
    for by_config in records.values():
        bare, rory = by_config[BARE], by_config['rory']
        if bare.error or rory.error or not rory.usage_by_role:
            continue
        node = float(rory.usage_by_role.get('node', {}).get('steady_cpu_percent', 0.0))
        pairs.append(Pair(bare.steady_cpu_percent, bare.pss_mb, rory.steady_cpu_percent,
                          rory.pss_mb, rory.steady_cpu_percent - node))
    return pairs, runs - len(pairs)


def stack_pairs(world: str, runs: int, out: Path, domain: int,
                progress: Callable[[str], None] = print) -> tuple[list[Pair], int]:
    """The six bare and the six under one supervisor, ``runs`` times alternating."""
    from rory_eval.bench.stack_bench import run_once

    records: dict[int, dict[str, dict[str, Any]]] = {}
    for repetition, config in alternating(CONFIGS, runs):
        began = time.monotonic()
        try:
            record = run_once(config, world, out / 'stack' / f'{config}-{repetition}', domain)
        except Exception as exc:  # a failed run is counted, not the end of the sitting
            progress(f'[{repetition + 1}/{runs}] stack {config}: ERROR {type(exc).__name__}: '
                     f'{exc}')
            continue
        records.setdefault(repetition, {})[config] = record
        progress(f'[{repetition + 1}/{runs}] stack {config}: {record["cpu_percent"]:.1f}% '
                 f'steady, {record["pss_mb"]:.0f} MB PSS, goal '
                 f'{"reached" if record["goal_reached"] else "NOT reached"} '
                 f'({time.monotonic() - began:.0f} s)')
    pairs = []
    for by_config in records.values():
        if BARE not in by_config or 'rory' not in by_config:
            continue
        bare, rory = by_config[BARE], by_config['rory']
        node = rory['roles'].get('node', {}).get('cpu_percent', 0.0)
        pairs.append(Pair(bare['cpu_percent'], bare['pss_mb'], rory['cpu_percent'],
                          rory['pss_mb'], rory['cpu_percent'] - node))
    return pairs, runs - len(pairs)


def load(folder: Path) -> dict[str, Any]:
    """A sitting's ``table_ii.json``."""
    path = folder / RESULT
    try:
        data: dict[str, Any] = json.loads(path.read_text())
        rows = [Row(**r) for r in data['rows']]
    except FileNotFoundError:
        raise TableIIError(f'{path}: no such file (not a folder this bench wrote)') from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise TableIIError(f'{path}: not a Table II result ({exc})') from None
    data['rows'] = rows
    return data


def merge(sittings: Sequence[dict[str, Any]]) -> list[Row]:
    """Every program's row; a program measured in two sittings is refused by name."""
    rows: dict[str, Row] = {}
    for sitting in sittings:
        for r in sitting['rows']:
            if r.program in rows:
                raise TableIIError(f'{r.program} is in two of the folders: give one of them')
            rows[r.program] = r
    return list(rows.values())


def report(sittings: Sequence[dict[str, Any]]) -> str:
    """The table and, per sitting, when, where, with what command and at what load."""
    lines = [table(merge(sittings)), '']
    for s in sittings:
        lines.append(f'- {s["date"]}, {s["minutes"]:.1f} min, world {s["world"]}, load average '
                     f'{s["load_before"]:.2f} before and {s["load_after"]:.2f} after: '
                     f'`{s["command"]}` ({", ".join(r.program for r in s["rows"])})')
    return '\n'.join(lines) + '\n'


def _load_average() -> float:
    return os.getloadavg()[0]


def main(argv: Sequence[str] | None = None) -> int:
    """Run a sitting (or merge sittings with --report); print and write the table."""
    from rory_eval.harness.simrun import exit_on_sigterm

    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog='python -m rory_eval.bench.table_ii',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--targets', nargs='*', default=list(TARGETS), choices=sorted(TARGETS))
    parser.add_argument('--runs', type=int, default=3, help='pairs per target')
    parser.add_argument('--stack-runs', type=int, default=3,
                        help='pairs of the six-target stack (0: leave the stack out)')
    parser.add_argument('--world', default='real_room', choices=WORLDS)
    parser.add_argument('--domain', type=int, default=88, help='ROS_DOMAIN_ID of the runs')
    parser.add_argument('--out', type=Path, default=Path('bench-out/table-ii'))
    parser.add_argument('--report', type=Path, nargs='+', metavar='DIR',
                        help='no runs: one table from the folders of earlier sittings')
    args = parser.parse_args(argv)
    if args.report:
        try:
            print(report([load(folder) for folder in args.report]), end='')
        except TableIIError as exc:
            print(f'table_ii: {exc}', file=sys.stderr)
            return 2
        return 0
    if args.runs < 1 or args.stack_runs < 0:
        parser.error('--runs must be at least 1 and --stack-runs at least 0')
    if not args.targets and not args.stack_runs:
        parser.error('nothing to run: no --targets and --stack-runs 0')
    exit_on_sigterm()
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    began, load_before = time.monotonic(), _load_average()
    date = f'{datetime.now(UTC):%Y-%m-%d %H:%M} UTC'
    rows = []
    for target in args.targets:
        pairs, failed = target_pairs(target, args.world, args.runs, out, args.domain)
        rows.append(row(target, pairs, failed))
    if args.stack_runs:
        pairs, failed = stack_pairs(args.world, args.stack_runs, out, args.domain)
        rows.append(row(STACK, pairs, failed))
    sitting = {'date': date, 'minutes': (time.monotonic() - began) / 60, 'world': args.world,
               'load_before': load_before, 'load_after': _load_average(),
               'command': shlex.join(['python', '-m', 'rory_eval.bench.table_ii', *argv]),
               'rows': rows}
    (out / RESULT).write_text(json.dumps({**sitting, 'rows': [asdict(r) for r in rows]},
                                         indent=1) + '\n')
    text = report([sitting])
    (out / 'table_ii.md').write_text(text)
    print(text, end='')
    return 0 if all(r.failed == 0 for r in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
