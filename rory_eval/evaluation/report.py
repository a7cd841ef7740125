"""The evaluation's tables, as in the paper, from the run records.

* Table I - restart vs RORY, correct or not, per target and world;
* Table II - overhead: CPU% and RSS of the bare node against node + RORY, and the ratios;
* Table III - checkpoint, replay and RORY, correct or not;
* Table IV - recovery time (crash detected -> released), median per target, world and method,
  and its breakdown into the steps S1-S4 (S3 split into restart, restore and replay).

Runs of a method at the other replay pace (``RunSpec.beside``) have their own column beside
the method's, e.g. ``rory paced`` next to ``rory``.

✓: every judged run correct; ✗: none; ?: some. A cell also shows ``k/n`` (correct of judged)
when not every repetition was judged (a run or its reference failed).
"""

from __future__ import annotations

import csv
import math
import statistics
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from rory_eval.evaluation.judge import Verdict, judge
from rory_eval.runs.plan import BARE, METHODS, WORLDS
from rory_eval.runs.runner import RECORD, RunRecord
from rory_eval.targets import TARGETS

# The recovery steps as the supervisor reports them (rory_runtime/supervisor/recovery.py).
STEPS = (('S1 safe state', ('s1_ms',)), ('S2 isolate', ('s2_ms',)),
         ('S3 restart', ('restart_ms',)), ('S3 restore', ('restore_ms',)),
         ('S3 replay', ('sync_ms', 'replay_ms')), ('S4 release', ('s4_ms',)))


@dataclass
class Judged:
    """A crash run, where it is, and its verdict."""

    record: RunRecord
    folder: Path
    verdict: Verdict


def judge_all(runs: Iterable[tuple[RunRecord, Path]]) -> list[Judged]:
    """Every crash run judged against the bare run of its target, world and repetition."""
    runs = list(runs)
    references = {(r.spec.target, r.spec.world, r.spec.repetition): (r, f)
                  for r, f in runs if r.spec.method == BARE}
    judged = []
    for record, folder in runs:
        spec = record.spec
        if spec.crash_at is None:
            continue
        ref = references.get((spec.target, spec.world, spec.repetition))
        if ref is None:
            verdict = Verdict(None, reason='no reference run')
        else:
            verdict = judge(spec.spec.kind, record, folder, ref[0], ref[1])
        judged.append(Judged(record, folder, verdict))
    return judged


def symbol(verdicts: Sequence[Verdict]) -> str:
    """✓ all correct, ✗ none, ? some; with k/n when some were not judged; '' if none ran."""
    if not verdicts:
        return ''
    judged = [v for v in verdicts if v.correct is not None]
    if not judged:
        return 'n/a'
    good = sum(bool(v.correct) for v in judged)
    mark = '✓' if good == len(judged) else ('✗' if good == 0 else '?')
    if len(judged) < len(verdicts) or mark == '?':
        return f'{mark} {good}/{len(judged)}' + (f' of {len(verdicts)}'
                                                 if len(judged) < len(verdicts) else '')
    return mark


def _present(values: Iterable[str], order: Sequence[str]) -> list[str]:
    seen = set(values)
    return [v for v in order if v in seen]


def _cell_table(judged: Sequence[Judged], methods: Sequence[str], first: str, align: str,
                cell: Callable[[str, str, str], str], label: Callable[[str], str]) -> str:
    """Targets down, world x method across, as the paper lays out its tables."""
    targets = _present((j.record.spec.target for j in judged), list(TARGETS))
    worlds = _present((j.record.spec.world for j in judged), WORLDS)
    methods = _present((j.record.spec.column for j in judged), methods)
    if not methods:
        return ''
    head = f'| {first} | ' + ' | '.join(f'{w} {m}' for w in worlds for m in methods) + ' |'
    lines = [head, '|---|' + f'{align}|' * (len(worlds) * len(methods))]
    for t in targets:
        cells = [cell(t, w, m) for w in worlds for m in methods]
        lines.append(f'| {label(t)} | ' + ' | '.join(cells) + ' |')
    return '\n'.join(lines)


def correctness_table(judged: Sequence[Judged], methods: Sequence[str]) -> str:
    """Targets x (world x method) of symbols, like the paper's Tables I and III."""
    by_cell: dict[tuple[str, str, str], list[Verdict]] = defaultdict(list)
    for j in judged:
        s = j.record.spec
        by_cell[(s.target, s.world, s.column)].append(j.verdict)
    return _cell_table(judged, methods, 'program (paper)', '---',
                       lambda t, w, m: symbol(by_cell.get((t, w, m), [])),
                       lambda t: f'{t} ({TARGETS[t].paper})')


def _median(values: Sequence[float]) -> str:
    return f'{statistics.median(values):.0f}' if values else '-'


def _total(recovery: dict[str, Any]) -> float:
    return float(recovery.get('total_ms', math.nan))


def columns(judged: Sequence[Judged], methods: Sequence[str] = METHODS) -> list[str]:
    """``methods``, each followed by its runs at the other replay pace when there are any."""
    beside = {(j.record.spec.method, j.record.spec.column) for j in judged
              if j.record.spec.beside}
    return [c for m in methods for c in (m, *sorted(c for b, c in beside if b == m))]


def recovery_table(judged: Sequence[Judged]) -> str:
    """Median recovery time (ms) per target x (world x method), like the paper's Table IV."""
    times: dict[tuple[str, str, str], list[float]] = defaultdict(list)
    for j in judged:
        s = j.record.spec
        if j.record.recoveries:
            times[(s.target, s.world, s.column)].append(_total(j.record.recoveries[0]))
    return _cell_table(judged, columns(judged), 'program', '---:',
                       lambda t, w, m: _median(times.get((t, w, m), [])), lambda t: t)


def steps_table(judged: Sequence[Judged]) -> str:
    """Median ms of each recovery step per target and method (all worlds together)."""
    rows: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for j in judged:
        s = j.record.spec
        if j.record.recoveries:
            rows[(s.target, s.column)].append(j.record.recoveries[0])
    lines = ['| program | method | runs | total | ' + ' | '.join(n for n, _ in STEPS) + ' |',
             '|---|---|---:|---:|' + '---:|' * len(STEPS)]
    targets = _present((t for t, _ in rows), list(TARGETS))
    order = columns(judged)
    for t in targets:
        for m in order:
            recs = rows.get((t, m))
            if not recs:
                continue
            steps = [_median([sum(float(r.get(k, 0.0)) for k in keys)
                              for r in recs]) for _, keys in STEPS]
            lines.append(f'| {t} | {m} | {len(recs)} | {_median([_total(r) for r in recs])} | '
                         + ' | '.join(steps) + ' |')
    return '\n'.join(lines)


def overhead_table(runs: Sequence[tuple[RunRecord, Path]]) -> str:
    """Mean CPU% and peak RSS of the bare node and of node + RORY without a crash, same
    workload (same target, world and repetition), with the ratios - like the paper's Table II."""
    pairs: dict[tuple[str, str, int], dict[str, RunRecord]] = defaultdict(dict)
    for record, _ in runs:
        s = record.spec
        if s.crash_at is None and not record.error:
            pairs[(s.target, s.world, s.repetition)][s.method] = record
    per_target: dict[tuple[str, str], list[tuple[RunRecord, RunRecord]]] = defaultdict(list)
    for (target, world, _), methods in pairs.items():
        if BARE in methods and 'rory' in methods:
            per_target[(target, world)].append((methods[BARE], methods['rory']))
    lines = ['| program | world | runs | original CPU | original RSS | RORY CPU | RORY RSS |',
             '|---|---|---:|---:|---:|---:|---:|']
    for target in TARGETS:
        for world in WORLDS:
            both = per_target.get((target, world))
            if not both:
                continue
            cpu0 = statistics.fmean(b.cpu_percent for b, _ in both)
            rss0 = statistics.fmean(b.peak_rss_mb for b, _ in both)
            cpu1 = statistics.fmean(r.cpu_percent for _, r in both)
            rss1 = statistics.fmean(r.peak_rss_mb for _, r in both)
            lines.append(f'| {target} | {world} | {len(both)} | {cpu0:.1f}% | {rss0:.0f} MB | '
                         f'{cpu1:.1f}% ({cpu1 / cpu0:.2f}x) | '
                         f'{rss1:.0f} MB ({rss1 / rss0:.2f}x, +{rss1 - rss0:.0f} MB) |')
    return '\n'.join(lines)


def overhead_by_process(runs: Sequence[tuple[RunRecord, Path]]) -> str:
    """Where Table II's overhead goes: per process role, CPU over the whole run and over its
    second half (steady: every process up, one-time start-up costs behind), peak RSS and PSS,
    for the bare node and for each process under RORY; means over the no-crash runs that
    recorded them (records from before this breakdown have none)."""
    by_cell: dict[tuple[str, str, str], list[RunRecord]] = defaultdict(list)
    for record, _ in runs:
        s = record.spec
        if s.crash_at is None and not record.error and record.usage_by_role:
            by_cell[(s.target, s.world, s.method)].append(record)
    lines = ['| program | world | run | process | CPU whole run | CPU steady | peak RSS | PSS |',
             '|---|---|---|---|---:|---:|---:|---:|']
    for target in TARGETS:
        for world in WORLDS:
            for method in (BARE, 'rory'):
                records = by_cell.get((target, world, method))
                if not records:
                    continue
                roles = [r for r in ('node', 'supervisor', 'zygote', 'standby', 'reaped')
                         if any(r in rec.usage_by_role for rec in records)]
                for role in roles:
                    lines.append(
                        f'| {target} | {world} | {method} | {role} | '
                        f'{_role_mean(records, role, "cpu_percent"):.1f}% | '
                        f'{_role_mean(records, role, "steady_cpu_percent"):.1f}% | '
                        f'{_role_mean(records, role, "peak_rss_mb"):.0f} MB | '
                        f'{_role_mean(records, role, "pss_mb"):.0f} MB |')
                if len(roles) > 1:
                    lines.append(
                        f'| {target} | {world} | {method} | **all** | '
                        f'{statistics.fmean(r.cpu_percent for r in records):.1f}% | '
                        f'{statistics.fmean(r.steady_cpu_percent for r in records):.1f}% | '
                        f'{statistics.fmean(r.peak_rss_mb for r in records):.0f} MB | '
                        f'{statistics.fmean(r.pss_mb for r in records):.0f} MB |')
    return '\n'.join(lines) if len(lines) > 2 else ''


def _role_mean(records: Sequence[RunRecord], role: str, key: str) -> float:
    """Mean of one figure of one role over records (a record without that role counts 0)."""
    return statistics.fmean(float(r.usage_by_role.get(role, {}).get(key, 0.0)) for r in records)


def running_time(runs: Sequence[tuple[RunRecord, Path]], *, gap: float = 600.0
                 ) -> tuple[float, int]:
    """Seconds the evaluation spent running, and in how many sittings.

    An interrupted evaluation is resumed later, so the time of the last call is not the
    evaluation's. Each run spans [end - wall_seconds, end], its end being when its record was
    written. Runs less than ``gap`` seconds apart belong to one sitting, which lasted from its
    first run's start to its last run's end; the running time is the sum over sittings.
    """
    spans = sorted(
        ((folder / RECORD).stat().st_mtime - record.wall_seconds,
         (folder / RECORD).stat().st_mtime)
        for record, folder in runs
        if record.wall_seconds > 0 and (folder / RECORD).exists()
    )
    sittings: list[list[float]] = []
    for begin, finish in spans:
        if sittings and begin - sittings[-1][1] <= gap:
            sittings[-1][1] = max(sittings[-1][1], finish)
        else:
            sittings.append([begin, finish])
    return sum(b - a for a, b in sittings), len(sittings)


def first_start(runs: Sequence[tuple[RunRecord, Path]]) -> datetime | None:
    """When the earliest run began (as :func:`running_time` spans them), or None if no run ran."""
    spans = [(folder / RECORD).stat().st_mtime - record.wall_seconds
             for record, folder in runs
             if record.wall_seconds > 0 and (folder / RECORD).exists()]
    return datetime.fromtimestamp(min(spans), UTC) if spans else None


def failures(judged: Sequence[Judged]) -> str:
    """One line per crash run that was not correct or not judged, with the reason."""
    lines = []
    for j in judged:
        if j.verdict.correct is not True:
            s = j.record.spec
            lines.append(f'- {s.target} {s.world} {s.column} r{s.repetition} '
                         f'(crash at {s.crash_at:g} s): {j.verdict.reason}')
    return '\n'.join(lines)


CSV_FIELDS = ('target', 'world', 'method', 'repetition', 'seed', 'crash_at', 'killed_at',
              'duration', 'replay', 'error', 'correct', 'reason', 'measures', 'total_ms',
              's1_ms', 's2_ms', 'restart_ms', 'restore_ms', 'sync_ms', 'replay_ms', 's4_ms',
              'replayed', 'crashes', 'cpu_percent', 'peak_rss_mb', 'wall_seconds', 'folder')


def write_csv(path: Path, runs: Sequence[tuple[RunRecord, Path]],
              judged: Sequence[Judged]) -> None:
    """Every run, one row: its spec, its verdict and measures, its recovery, its usage."""
    verdicts = {id(j.record): j.verdict for j in judged}
    with path.open('w', newline='') as f:
        writer = csv.DictWriter(f, fieldnames=CSV_FIELDS)
        writer.writeheader()
        for record, folder in runs:
            s = record.spec
            v = verdicts.get(id(record))
            rec = record.recoveries[0] if record.recoveries else {}
            row: dict[str, object] = {
                'target': s.target, 'world': s.world, 'method': s.method,
                'repetition': s.repetition, 'seed': s.seed, 'crash_at': s.crash_at,
                'killed_at': (None if record.killed_at is None
                              else round(record.killed_at, 3)),
                'duration': s.duration, 'replay': s.replay, 'error': record.error,
                'correct': '' if v is None or v.correct is None else int(v.correct),
                'reason': v.reason if v else '',
                'measures': ' '.join(f'{k}={x:.4g}' for k, x in v.measures.items()) if v else '',
                'cpu_percent': round(record.cpu_percent, 2),
                'peak_rss_mb': round(record.peak_rss_mb, 1),
                'wall_seconds': round(record.wall_seconds, 1), 'folder': str(folder),
            }
            for key in ('total_ms', 's1_ms', 's2_ms', 'restart_ms', 'restore_ms', 'sync_ms',
                        'replay_ms', 's4_ms', 'replayed', 'crashes'):
                row[key] = rec.get(key, '')
            writer.writerow(row)
