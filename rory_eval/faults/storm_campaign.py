"""``make faults``, crash storms: the same node struck again and again, soon after each recovery.

A robot's crash loops are this: a fault fires, RORY recovers the node, and the same fault fires
again a moment later, while the replacement replays, just after its release, before its first
checkpoint, or between two checkpoints. Each run here is the integrator scenario (real
supervisor, real node, real publisher of 1..N at 50 Hz, ``rory_eval/faults/flaky``) struck by a
*schedule*: 1-5 strikes, each a gap after the previous one (0.05 s to two checkpoint
intervals), each a fault (SIGKILL, SIGSEGV, an uncaught exception, a hang the heartbeat
finds), with paced or fast replay, from a warm standby or cold. The campaign draws each
schedule on its own from a seed (:func:`random_schedule`); the tests draw from the same space
with Hypothesis (:func:`schedules`), whose boundaries come up early. A run is correct when the
node's final history is exactly 1..N, in order (a message the supervisor quarantined as
poison, two strikes having landed on it, is left out of N and counted); lost and applied-twice
numbers are counted one by one.

A schedule that goes wrong is written to ``tests/integration/storm_schedules.json``, where
``tests/integration/test_storm_campaign.py`` replays every one of them as a regression case.

    python -m rory_eval.faults.storm_campaign --runs 40            # the campaign (~12 min here)
    python -m rory_eval.faults.storm_campaign --issue-schedule 20  # issue 21's, 20 x 4 ways
"""

from __future__ import annotations

import argparse
import json
import random
import shutil
import sys
import tempfile
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hypothesis import strategies as st

from rory_eval.faults.fault_campaign import FLAKY
from rory_eval.harness.scenario import Kill, ScenarioResult, run
from rory_eval.harness.simrun import exit_on_sigterm
from rory_runtime.protocol import seq_ranges

FAULTS = ('SIGKILL', 'SIGSEGV', 'raise', 'hang')
RATE = 50.0
INTERVAL = 2.0  # checkpoint interval of the runs (s): the default users run
REGRESSIONS = Path(__file__).resolve().parents[2] / 'tests' / 'integration' / \
    'storm_schedules.json'


@dataclass(frozen=True)
class Strike:
    """One fault, ``gap`` seconds after the previous strike (the first: after the first
    number the node applied)."""

    gap: float
    fault: str


@dataclass(frozen=True)
class Schedule:
    """One run: its strikes, the replay pace, and whether replacements start warm."""

    strikes: tuple[Strike, ...]
    pace: str = 'fast'
    warm: bool = True
    interval: float = INTERVAL
    numbers: int | None = None  # how many the publisher sends; None: :attr:`count` decides

    @property
    def count(self) -> int:
        """Numbers published: by default the stream outlasts the strikes, their recoveries and
        backoffs (a raise or hang strikes only when the node applies a number)."""
        if self.numbers is not None:
            return self.numbers
        span = sum(s.gap for s in self.strikes) + 1.5 * len(self.strikes) + 3.0
        return int(RATE * span)

    def kills(self) -> tuple[Kill, ...]:
        """The scenario's strikes."""
        return tuple(Kill(after_previous=s.gap, how=s.fault) for s in self.strikes)

    def label(self) -> str:
        """One line."""
        strikes = ', '.join(f'{s.fault}+{s.gap:.2f}' for s in self.strikes)
        return f'[{strikes}] {self.pace} {"warm" if self.warm else "cold"}'

    def to_json(self) -> dict[str, Any]:
        """For the regression file."""
        return asdict(self)

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Schedule:
        """From the regression file."""
        return cls(
            strikes=tuple(Strike(float(s['gap']), str(s['fault'])) for s in data['strikes']),
            pace=str(data.get('pace', 'fast')),
            warm=bool(data.get('warm', True)),
            interval=float(data.get('interval', INTERVAL)),
            numbers=None if data.get('numbers') is None else int(data['numbers']),
        )


ISSUE_21 = tuple(
    Schedule((Strike(3.1, 'SIGKILL'), Strike(2.5, 'SIGKILL'), Strike(2.5, 'SIGKILL')),
             pace, warm, interval=2.0, numbers=600)
    for pace in ('paced', 'fast') for warm in (True, False)
)
"""Issue 21's report: 600 numbers at 50 Hz, SIGKILLed three times 2.5 s apart from 3.1 s in,
2 s checkpoints; paced and fast replay, warm and cold starts."""


MAX_STRIKES = 5
FIRST = (0.3, 2.0)  # the first strike, in checkpoint intervals after the first number...
GAP = (0.05, 2.0)  # ...and each next one after the previous (the lower bound in seconds)


def _bounds(interval: float) -> tuple[tuple[float, float], tuple[float, float]]:
    return (FIRST[0], FIRST[1] * interval), (GAP[0], GAP[1] * interval)


def schedules(interval: float = INTERVAL) -> st.SearchStrategy[Schedule]:
    """Hypothesis: 1-5 strikes; the first 0.3 s to two intervals into the stream, each next
    one 0.05 s to two checkpoint intervals after the previous; any fault; either pace; warm or
    cold. Its boundaries (the shortest gaps, the most strikes) come up early."""
    first, gap = _bounds(interval)

    def strike(bounds: tuple[float, float]) -> st.SearchStrategy[Strike]:
        return st.builds(Strike, gap=st.floats(*bounds).map(lambda g: round(g, 2)),
                         fault=st.sampled_from(FAULTS))

    return st.builds(
        lambda head, tail, pace, warm: Schedule((head, *tail), pace, warm, interval),
        strike(first), st.lists(strike(gap), min_size=0, max_size=MAX_STRIKES - 1),
        st.sampled_from(('paced', 'fast')), st.booleans(),
    )


def random_schedule(rng: random.Random, interval: float = INTERVAL) -> Schedule:
    """The same space as :func:`schedules`, drawn uniformly: the campaign's draws.

    Hypothesis, given few examples, spends most of them on variations of one schedule; a
    campaign of real runs wants each draw independent of the others.
    """
    first, gap = _bounds(interval)
    count = rng.randint(1, MAX_STRIKES)
    strikes = [Strike(round(rng.uniform(*(first if i == 0 else gap)), 2), rng.choice(FAULTS))
               for i in range(count)]
    return Schedule(tuple(strikes), rng.choice(('paced', 'fast')), rng.random() < 0.5, interval)


@dataclass
class Outcome:
    """What one run showed."""

    schedule: Schedule
    correct: bool
    expected: int
    lost: int = 0
    duplicated: int = 0
    out_of_order: bool = False
    gave_up: bool = False
    strikes: int = 0  # strikes the harness delivered
    crashes: int = 0  # crashes the recoveries covered
    recoveries: int = 0
    quarantined: list[int] = field(default_factory=list)
    never_delivered: int = 0
    error: str = ''
    missing: str = ''
    twice: str = ''


def judge(schedule: Schedule, result: ScenarioResult) -> Outcome:
    """Correct = the history is exactly 1..N in order, less what was quarantined as poison."""
    quarantined = sorted(
        int(e['seq']) for e in result.events if e['kind'] == 'quarantined'
    )  # the publisher's sequence number is the number it sent (1..N)
    expected = [n for n in range(1, result.expected + 1) if n not in set(quarantined)]
    history = result.history
    seen = Counter(history)
    lost = [n for n in expected if n not in seen]
    twice = sorted(n for n, c in seen.items() if c > 1)
    states = [e.get('new') for e in result.events if e['kind'] == 'state']
    never = sum(int(d.get('count', 0)) for r in result.recoveries
                for d in (r.get('never_delivered') or {}).values())
    return Outcome(
        schedule, history == expected, result.expected, lost=len(lost),
        duplicated=sum(c - 1 for c in seen.values()),
        out_of_order=history != sorted(history), gave_up='FATAL' in states,
        strikes=len(result.kills), crashes=sum(int(r.get('crashes', 1))
                                               for r in result.recoveries),
        recoveries=len(result.recoveries), quarantined=quarantined, never_delivered=never,
        missing=seq_ranges(lost, sep=','), twice=seq_ranges(twice, sep=','),
    )


def scenario(schedule: Schedule, workdir: Path, domain_id: int,
             timeout: float = 150.0) -> ScenarioResult:
    """The run of ``schedule`` (no strikes: a run without a fault, as the load campaign
    makes); raises RuntimeError when the harness fails."""
    return run('rory', schedule.kills(), workdir, domain_id=domain_id, count=schedule.count,
               rate=RATE, interval=schedule.interval, pace=schedule.pace, program=FLAKY,
               warm_standby=schedule.warm, timeout=timeout)


def run_schedule(schedule: Schedule, workdir: Path, domain_id: int,
                 timeout: float = 150.0) -> Outcome:
    """One run in its own folder and ROS domain; a harness failure is an outcome too."""
    try:
        result = scenario(schedule, workdir, domain_id, timeout)
    except RuntimeError as err:
        return Outcome(schedule, False, schedule.count, lost=schedule.count,
                       error=str(err).splitlines()[0])
    return judge(schedule, result)


def describe(outcome: Outcome) -> str:
    """The verdict of one run, one line."""
    if outcome.correct:
        extra = f', {len(outcome.quarantined)} quarantined' if outcome.quarantined else ''
        return f'ok ({outcome.strikes} strikes, {outcome.recoveries} recoveries{extra})'
    return (f'WRONG: lost {outcome.lost} ({outcome.missing}), twice {outcome.duplicated} '
            f'({outcome.twice}){", out of order" if outcome.out_of_order else ""}'
            f'{", gave up" if outcome.gave_up else ""} {outcome.error}')


def table(outcomes: Sequence[Outcome]) -> str:
    """Markdown: per number of strikes, per fault present, per pace and start, and in all."""
    lines = ['| schedules | runs | exact | strikes | crashes recovered | messages | lost '
             '| applied twice | quarantined | never delivered | give-ups |',
             '|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|']

    def row(name: str, group: Sequence[Outcome]) -> None:
        if not group:
            return
        lines.append(
            f'| {name} | {len(group)} | {sum(o.correct for o in group)} '
            f'| {sum(o.strikes for o in group)} | {sum(o.crashes for o in group)} '
            f'| {sum(o.expected for o in group)} | {sum(o.lost for o in group)} '
            f'| {sum(o.duplicated for o in group)} | {sum(len(o.quarantined) for o in group)} '
            f'| {sum(o.never_delivered for o in group)} | {sum(o.gave_up for o in group)} |')

    for n in range(1, 6):
        row(f'{n} strike{"s" if n > 1 else ""}',
            [o for o in outcomes if len(o.schedule.strikes) == n])
    for fault in FAULTS:
        row(f'with {fault}',
            [o for o in outcomes if any(s.fault == fault for s in o.schedule.strikes)])
    for pace in ('paced', 'fast'):
        for warm in (True, False):
            row(f'{pace}, {"warm" if warm else "cold"}',
                [o for o in outcomes if o.schedule.pace == pace and o.schedule.warm == warm])
    row('**all**', outcomes)
    return '\n'.join(lines)


def load_regressions(path: Path = REGRESSIONS) -> list[Schedule]:
    """The schedules kept because they once went wrong."""
    if not path.exists():
        return []
    return [Schedule.from_json(item['schedule'])
            for item in json.loads(path.read_text())['schedules']]


def keep_regression(outcome: Outcome, path: Path = REGRESSIONS) -> None:
    """Add a wrong run's schedule to the regression file (once)."""
    data = json.loads(path.read_text()) if path.exists() else {'schedules': []}
    item = outcome.schedule.to_json()
    if any(kept['schedule'] == item for kept in data['schedules']):
        return
    data['schedules'].append({'schedule': item, 'found': describe(outcome)})
    path.write_text(json.dumps(data, indent=1) + '\n')


def campaign(runs: int, seed: int) -> list[Schedule]:
    """``runs`` schedules, the same ones for the same seed."""
    return [random_schedule(random.Random(f'{seed}-{i}')) for i in range(runs)]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the campaign; exit 1 unless every run recovered exactly."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.faults.storm_campaign',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=40, help='schedules to draw')
    parser.add_argument('--seed', type=int, default=21)
    parser.add_argument('--issue-schedule', type=int, metavar='N', default=0,
                        help="run issue 21's schedule N times in each pace and start instead")
    parser.add_argument('--regressions', action='store_true',
                        help='run the kept regression schedules instead')
    parser.add_argument('--domain', type=int, default=91, help='ROS domain id to use')
    parser.add_argument('--out', help='keep the runs here (default: a temporary folder)')
    parser.add_argument('--no-keep', action='store_true',
                        help='do not add wrong schedules to the regression file')
    args = parser.parse_args(argv)
    if args.runs < 1 or args.issue_schedule < 0:
        parser.error('--runs must be at least 1 and --issue-schedule at least 0')
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-storms-'))
    outcomes: list[Outcome] = []

    def each(schedule: Schedule) -> None:
        i = len(outcomes)
        workdir = root / f'run{i:03d}'
        outcome = run_schedule(schedule, workdir, args.domain)
        outcomes.append(outcome)
        print(f'[{i + 1}] {schedule.label()}: {describe(outcome)}'
              f'{"" if outcome.correct else f" -> {workdir}"}', flush=True)
        if not outcome.correct and not args.no_keep:
            keep_regression(outcome)
        elif outcome.correct and not args.out:
            shutil.rmtree(workdir, ignore_errors=True)

    if args.issue_schedule:
        for _ in range(args.issue_schedule):
            for schedule in ISSUE_21:
                each(schedule)
    elif args.regressions:
        for schedule in load_regressions():
            each(schedule)
    else:
        for schedule in campaign(args.runs, args.seed):
            each(schedule)
    print()
    print(table(outcomes))
    if not args.out and all(o.correct for o in outcomes):
        shutil.rmtree(root, ignore_errors=True)
    return 0 if all(o.correct for o in outcomes) else 1


if __name__ == '__main__':
    sys.exit(main())
