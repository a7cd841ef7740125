"""``rory eval`` / ``make eval``: every target x world x method x repetition, then the tables.

    python -m rory_eval.evaluation [--quick] [--targets T ...] [--worlds W ...]
        [--methods M ...] [--repetitions 5] [--crash-at 9 | --random-crash]
        [--replay fast|paced] [--other-pace [METHOD ...]] [--jobs 1] [--out eval-out] [--fresh]
        [--report-only] [--table-ii DIR ...]

Each run is its own process (:mod:`rory_eval.runs.runner`) in its own ROS domain; its record
is kept in ``OUT/runs/NAME/``, so an interrupted evaluation goes on where it stopped
(``--fresh`` starts over; ``--report-only`` runs nothing and reports what is recorded). At the
end it judges every crash run against its reference (:mod:`.judge`) and writes
``OUT/results.md`` (the tables, the failures, the settings, the machine, the command and how
long it took), ``OUT/runs.csv`` (one row per run) and ``OUT/figures/*.png``.

The evaluation's own overhead runs share the machine with its other runs. The paper's Table II
is measured on a quiet machine by :mod:`rory_eval.bench.table_ii`; ``--table-ii`` puts the
folders of its sittings into results.md as Table II.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import queue
import shlex
import subprocess
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from datetime import UTC, datetime
from pathlib import Path

from rory_eval.evaluation import judge as judge_module
from rory_eval.runs.plan import (
    CRASH_AT,
    METHODS,
    PACED_METHODS,
    PACES,
    WORLDS,
    Plan,
    RunSpec,
    build_plan,
    opposite_pace,
)
from rory_eval.runs.runner import RECORD, RunRecord, instrument
from rory_eval.targets import TARGETS

QUICK_TARGET = 'grid_slam'
QUICK_WORLD = 'office_small'
QUICK_SECONDS = 20.0  # sim s per run: 9 s before the crash, 11 s after


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(prog='rory eval', description=__doc__.split('\n\n')[0])
    parser.add_argument('--quick', action='store_true',
                        help=f'one target ({QUICK_TARGET}), one world ({QUICK_WORLD}), every '
                             f'method, one repetition of {QUICK_SECONDS:g} s (a few minutes)')
    parser.add_argument('--targets', nargs='+', choices=list(TARGETS), default=list(TARGETS))
    parser.add_argument('--worlds', nargs='+', choices=WORLDS, default=list(WORLDS))
    parser.add_argument('--methods', nargs='+', choices=METHODS, default=list(METHODS))
    parser.add_argument('--repetitions', type=int, default=5, help='runs per cell (paper: 5)')
    crash = parser.add_mutually_exclusive_group()
    crash.add_argument('--crash-at', type=float, default=CRASH_AT,
                       help='sim seconds into the run (paper: 9)')
    crash.add_argument('--random-crash', action='store_true',
                       help='a uniformly random crash time per repetition (seeded)')
    parser.add_argument('--duration', type=float, default=None,
                        help='sim seconds per run (default: per target kind, see '
                             'rory_eval/runs/plan.py)')
    parser.add_argument('--replay', choices=PACES, default='fast',
                        help="replay pace of rory and replay (paced: the paper's)")
    parser.add_argument('--other-pace', nargs='*', choices=PACED_METHODS, default=None,
                        metavar='METHOD',
                        help='methods that also crash once per cell with the other replay pace '
                             '(paced when --replay is fast), a column beside their own in '
                             'Tables III and IV (default: rory when it is among --methods; '
                             'none with --quick)')
    parser.add_argument('--overhead-worlds', nargs='*', choices=WORLDS, default=['real_room'],
                        help='worlds where a no-crash run under RORY measures the overhead '
                             '(paper: real_room)')
    parser.add_argument('--seed', type=int, default=0, help='base simulator seed (+ repetition)')
    parser.add_argument('--jobs', type=int, default=1,
                        help='runs at once (each takes about half a core)')
    parser.add_argument('--domain', type=int, default=100,
                        help='first ROS_DOMAIN_ID; the runs use the next --jobs ones (keep them '
                        '<= 101: higher ids have ports in the ephemeral range)')
    parser.add_argument('--out', type=Path, default=Path('eval-out'))
    parser.add_argument('--fresh', action='store_true', help='redo runs already recorded')
    parser.add_argument('--report-only', action='store_true',
                        help='run nothing: the tables from the runs recorded in --out (one not '
                             'recorded is reported as failed to run)')
    parser.add_argument('--table-ii', type=Path, nargs='+', default=[], metavar='DIR',
                        help='Table II from these folders of python -m rory_eval.bench.table_ii '
                             '(a quiet machine), instead of this evaluation\'s overhead runs')
    args = parser.parse_args(argv)
    if args.report_only and args.fresh:
        parser.error('--report-only and --fresh: one runs nothing, the other everything again')
    if args.other_pace is None:
        args.other_pace = [] if args.quick or 'rory' not in args.methods else ['rory']
    if args.quick:
        args.targets, args.worlds, args.repetitions = [QUICK_TARGET], [QUICK_WORLD], 1
        args.overhead_worlds = [QUICK_WORLD]
        args.duration = args.duration or QUICK_SECONDS
    if args.repetitions < 1 or args.jobs < 1:
        parser.error('--repetitions and --jobs must be at least 1')
    return args


class Progress:
    """A progress bar on stderr: runs done, elapsed, an estimate of what is left."""

    def __init__(self, total: int, width: int = 30) -> None:
        self.total, self.width, self.done = total, width, 0
        self.started = time.monotonic()
        self.tty = sys.stderr.isatty()

    def update(self, text: str) -> None:
        """One more run done; ``text`` says which and how it went."""
        self.done += 1
        elapsed = time.monotonic() - self.started
        left = elapsed / self.done * (self.total - self.done)
        filled = round(self.width * self.done / self.total)
        bar = '#' * filled + '.' * (self.width - filled)
        line = (f'[{bar}] {self.done}/{self.total} runs, {elapsed / 60:.1f} min, '
                f'~{left / 60:.1f} min left | {text}')
        print(('\r' + line + '\x1b[K') if self.tty else line, end='' if self.tty else '\n',
              file=sys.stderr, flush=True)

    def close(self) -> None:
        """End the bar's line."""
        if self.tty:
            print(file=sys.stderr)


def _load_if_done(spec: RunSpec, folder: Path) -> RunRecord | None:
    """A record already made for exactly this spec (and not a failed run)."""
    if not (folder / RECORD).exists():
        return None
    try:
        record = RunRecord.load(folder)
    except (ValueError, TypeError, KeyError):
        return None
    return record if record.run == spec.to_json() and not record.error else None


def _recorded(spec: RunSpec, folder: Path) -> RunRecord:
    """The record made for exactly this spec, failed or not; else one saying it is missing."""
    try:
        record = RunRecord.load(folder)
    except (OSError, ValueError, TypeError, KeyError):
        return RunRecord(run=spec.to_json(), error=f'not recorded in {folder}')
    if record.run != spec.to_json():
        return RunRecord(run=spec.to_json(), error=f'{folder} holds another run\'s record')
    return record


def execute_plan(plan: Plan, out: Path, *, jobs: int, domain: int, fresh: bool,
                 progress: Progress | None = None,
                 report_only: bool = False) -> list[tuple[RunRecord, Path]]:
    """Run every spec (``jobs`` at a time, each in its own domain); the records in plan order.
    With ``report_only``, nothing runs: the records as they are."""
    if report_only:
        return [(_recorded(spec, out.resolve() / 'runs' / spec.name),
                 out.resolve() / 'runs' / spec.name) for spec in plan.runs]
    # Absolute: the supervisor respawns the node from its own working directory.
    out = out.resolve()
    inst = out / 'instrumented'
    for target in sorted({r.target for r in plan.runs}):
        instrument(TARGETS[target], inst / target)
    domains: queue.Queue[int] = queue.Queue()
    for k in range(jobs):
        domains.put(domain + k)
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join(
        p for p in (str(Path(__file__).resolve().parents[2]), env.get('PYTHONPATH', '')) if p)

    def one(spec: RunSpec) -> tuple[RunRecord, Path]:
        folder = out / 'runs' / spec.name
        if not fresh:
            done = _load_if_done(spec, folder)
            if done is not None:
                return done, folder
        folder.mkdir(parents=True, exist_ok=True)
        (folder / 'spec.json').write_text(json.dumps(spec.to_json()) + '\n')
        slot = domains.get()
        try:
            with (folder / 'runner.log').open('wb') as log:
                subprocess.run(
                    [sys.executable, '-m', 'rory_eval.runs.runner',
                     str(folder / 'spec.json'), '--out', str(folder), '--domain', str(slot),
                     '--instrumented', str(inst / spec.target)],
                    stdout=log, stderr=subprocess.STDOUT, env=env, check=False,
                    timeout=spec.duration * 3 + 240)
        except subprocess.TimeoutExpired:
            RunRecord(run=spec.to_json(), error='the run timed out').save(folder)
        finally:
            domains.put(slot)
        if not (folder / RECORD).exists():
            RunRecord(run=spec.to_json(),
                      error=f'the runner left no record (see {folder}/runner.log)').save(folder)
        return RunRecord.load(folder), folder

    results: dict[int, tuple[RunRecord, Path]] = {}
    with ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(one, spec): k for k, spec in enumerate(plan.runs)}
        for future in as_completed(futures):
            record, folder = future.result()
            results[futures[future]] = (record, folder)
            if progress is not None:
                progress.update(_one_line(record))
    return [results[k] for k in range(len(plan.runs))]


def _one_line(record: RunRecord) -> str:
    s = record.spec
    what = f'{s.target} {s.world} {s.column}' + (
        '' if s.crash_at is None else f' crash {s.crash_at:g} s')
    if record.error:
        return f'{what}: FAILED ({record.error[:80]})'
    rec = record.recoveries
    return what + (f': recovered in {rec[0]["total_ms"]:.0f} ms' if rec else ': done')


def _machine() -> str:
    model = ''
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                model = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    return (f'{platform.node()}: {os.cpu_count()} CPUs ({model or platform.machine()}), '
            f'{platform.system()} {platform.release()}, Python {platform.python_version()}')


def write_results(args: argparse.Namespace, argv: Sequence[str],
                  runs: Sequence[tuple[RunRecord, Path]], started: datetime,
                  seconds: float, table_ii: Sequence[str] = ()) -> Path:
    """results.md, runs.csv and the figures, in args.out; ``table_ii`` is the quiet Table II's
    section (:func:`_table_ii`), if any."""
    from rory_eval.evaluation import figures, report

    judged = report.judge_all(runs)
    busy, sittings = report.running_time(runs)
    # When the runs began, not this call: a report made again later keeps the evaluation's date.
    began = report.first_start(runs) or started
    report.write_csv(args.out / 'runs.csv', runs, judged)
    pngs = figures.all_figures(runs, judged, args.out / 'figures')
    crash = 'uniformly random per repetition' if args.random_crash else f'{args.crash_at:g} s'
    failed_runs = [f'- {r.spec.name}: {r.error}' for r, _ in runs if r.error]
    length = (f'{args.duration:g} s' if args.duration
              else '30 s (mapping), to the goal (driving)')
    text = [
        '# RORY evaluation: the paper\'s tables from real runs',
        '',
        f'- date: {began:%Y-%m-%d %H:%M} UTC; {len(runs)} runs took {busy / 60:.1f} min in '
        f'{sittings} sitting{"s" if sittings != 1 else ""} (this call: {seconds / 60:.1f} min)',
        f'- machine: {_machine()}',
        f'- command: `{shlex.join(["rory", "eval", *argv])}`',
        f'- targets: {", ".join(args.targets)}; worlds: {", ".join(args.worlds)}; methods: '
        f'{", ".join(args.methods)}; repetitions: {args.repetitions}; seeds from {args.seed}',
        f'- crash: SIGKILL at {crash}; checkpoint every 2 s; replay {args.replay}'
        + (f' ({", ".join(args.other_pace)} also {opposite_pace(args.replay)}, beside)'
           if args.other_pace else '') + f'; run length: {length}',
        '',
        'Correctness (✓ every run correct, ✗ none, ? some; k/n = correct/judged), judged against '
        'the same target\'s run without a crash:',
        '',
        judge_module.criteria(),
        '',
        '## Table I: restart (ROS respawn) against RORY',
        '',
        report.correctness_table(judged, ('restart', 'rory')),
        '',
        '## Table III: checkpoint alone, replay alone and RORY',
        '',
        report.correctness_table(judged, report.columns(judged, ('checkpoint', 'replay',
                                                                  'rory'))),
        '',
        '## Table IV: recovery time, crash detected -> released (median ms)',
        '',
        report.recovery_table(judged),
        '',
        'Where the time goes (median ms per step, all worlds):',
        '',
        report.steps_table(judged),
        '',
        *table_ii,
        ('## Table II: overhead, the bare node against node + RORY (no crash, same workload)'
         if not args.table_ii else
         '## Overhead under the evaluation\'s load (no crash, same workload)'),
        '',
        'CPU in % of one core over the simulated run; RSS the peak of every process of the '
        'target (supervisor and node under RORY), summed. These runs share the machine with '
        'the evaluation\'s others.',
        '',
        report.overhead_table(runs) or '(no overhead runs)',
        '',
        *(['Per process (whole run; steady = its second half, every process up; PSS splits '
           'shared libraries between the processes that map them):', '', breakdown, '']
          if (breakdown := report.overhead_by_process(runs)) else []),
        '## Runs not correct or not judged',
        '',
        report.failures(judged) or 'none',
        '',
        '## Runs that failed to run',
        '',
        '\n'.join(failed_runs) or 'none',
        '',
        '## Figures',
        '',
        *[f'![{p.stem}](figures/{p.name})' for p in pngs],
        '',
    ]
    path = Path(args.out) / 'results.md'
    path.write_text('\n'.join(text))
    return path


def _table_ii(folders: Sequence[Path]) -> list[str]:
    """results.md's Table II from the quiet sittings of rory_eval.bench.table_ii, if given."""
    if not folders:
        return []
    from rory_eval.bench import table_ii

    sittings = [table_ii.load(folder) for folder in folders]
    return ['## Table II: overhead, the bare node against node + RORY (no crash, same workload)',
            '',
            'Measured on a quiet machine by `python -m rory_eval.bench.table_ii`: steady CPU (the '
            'second half of the run, every process up) in % of one core, PSS at the end, the '
            'simulator left out; ratio and PSS added are medians of the pairs (each RORY run '
            'against the bare run beside it).',
            '',
            table_ii.report(sittings)]


def main(argv: Sequence[str] | None = None) -> int:
    """Plan, run, report. Exit 0 when every run ran (whatever the verdicts), 1 otherwise."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv)
    try:
        plan = build_plan(args.targets, args.worlds, args.methods,
                          repetitions=args.repetitions, crash_at=args.crash_at,
                          random_crash=args.random_crash, duration=args.duration,
                          seed=args.seed, replay=args.replay,
                          overhead_worlds=args.overhead_worlds, other_pace=args.other_pace)
    except ValueError as exc:
        print(f'rory eval: {exc}', file=sys.stderr)
        return 2
    from rory_eval.bench.table_ii import TableIIError

    try:
        # Read before the runs: a wrong folder fails now, not after hours of them.
        table_ii = _table_ii(args.table_ii)
    except TableIIError as exc:
        print(f'rory eval: --table-ii: {exc}', file=sys.stderr)
        return 2
    if args.report_only and not (args.out / 'runs').is_dir():
        print(f'rory eval: --report-only: {args.out / "runs"} does not exist (no runs recorded '
              'there)', file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    started = datetime.now(UTC)
    t0 = time.monotonic()
    print(f'rory eval: {len(plan.runs)} runs ({len(plan.crash_runs())} with a crash) '
          f'{"recorded in" if args.report_only else "into"} {args.out}/', file=sys.stderr)
    progress = Progress(len(plan.runs))
    runs = execute_plan(plan, args.out, jobs=args.jobs, domain=args.domain, fresh=args.fresh,
                        progress=None if args.report_only else progress,
                        report_only=args.report_only)
    progress.close()
    path = write_results(args, argv, runs, started, time.monotonic() - t0, table_ii)
    print(path.read_text().split('## Runs not correct')[0])
    print(f'rory eval: results in {path}, {args.out / "runs.csv"}, {args.out / "figures"}/')
    return 1 if any(r.error for r, _ in runs) else 0
