"""``make faults``: strike a node under RORY with every kind of fault, check nothing is lost.

Each run is the integrator scenario (real supervisor, real node, real publisher of 1..N) with
a fault-injectable integrator (``rory_eval/faults/flaky``) struck at a random moment by one of:
SIGKILL, SIGSEGV, SIGABRT (signals from outside), an uncaught exception in its callback, or a
callback that hangs (found by the heartbeat, then killed). Half the runs strike a second time
soon after the replacement is spawned (while it starts, restores or replays, or just after its
release when the restart was quick). A run is correct when the node's final history is exactly
1..N: nothing lost, nothing applied twice. The table counts, per fault: runs, correct
recoveries, numbers lost, numbers applied twice and give-ups (a node left FATAL).

    python -m rory_eval.faults.fault_campaign                # the full campaign (~10 min here)
    python -m rory_eval.faults.fault_campaign --short        # one run per fault, two double faults
"""

from __future__ import annotations

import argparse
import random
import shutil
import sys
import tempfile
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from rory_eval.harness.scenario import Kill, Program, ScenarioResult, run
from rory_eval.harness.simrun import exit_on_sigterm
from rory_runtime.protocol import seq_ranges

FLAKY_DIR = Path(__file__).resolve().parent / 'flaky'
FLAKY = Program(FLAKY_DIR, FLAKY_DIR / 'keyvars.yaml', 'flaky_integrator.py',
                '/integrator/state', 'integrator', settings=(('hang_timeout', 1.0),))
FAULTS = ('SIGKILL', 'SIGSEGV', 'SIGABRT', 'raise', 'hang')
COUNT = 300
RATE = 50.0


@dataclass(frozen=True)
class Case:
    """One run of the campaign."""

    fault: str
    at: float  # seconds after the first number
    second: float | None  # seconds after the replacement's spawn for a second strike, or None

    def kills(self) -> tuple[Kill, ...]:
        first = Kill(after=self.at, how=self.fault)
        if self.second is None:
            return (first,)
        return (first, Kill(after_respawn=self.second, how=self.fault))

    def label(self) -> str:
        again = '' if self.second is None else f', again {self.second:.2f} s after the respawn'
        return f'{self.fault} at {self.at:.2f} s{again}'


@dataclass
class Outcome:
    """What one run showed."""

    case: Case
    correct: bool
    lost: int
    duplicated: int
    gave_up: bool
    recoveries: int
    error: str = ''
    strikes: int = 0  # faults the harness delivered
    covered: int = 0  # crashes the recoveries say they covered (a strike during a recovery
    # is covered by that same recovery, one after its release by a recovery of its own)
    missing: str = ''  # the numbers lost, as ranges


def plan(runs_per_fault: int, seed: int) -> list[Case]:
    """Random strike times (seeded), half of them with a second strike during recovery."""
    rng = random.Random(seed)
    cases = []
    for fault in FAULTS:
        for i in range(runs_per_fault):
            at = rng.uniform(0.5, COUNT / RATE - 1.5)
            # From the replacement's start to its release takes ~0.1-0.3 s from a warm
            # standby and 1.5-2.5 s cold (when the second strike kills the process that
            # replaced the standby): strike anywhere from inside it to well after it.
            second = rng.uniform(0.02, 2.0) if i % 2 == 1 else None
            cases.append(Case(fault, round(at, 2), None if second is None else round(second, 2)))
    return cases


def short_plan() -> list[Case]:
    """CI: every fault once, and a second strike during recovery for two of them."""
    cases = [Case(fault, 2.0, None) for fault in FAULTS]
    cases += [Case('SIGKILL', 2.5, 0.5), Case('raise', 1.5, 0.1)]
    return cases


def judge(case: Case, result: ScenarioResult) -> Outcome:
    """Correct = the history is exactly 1..N."""
    history = result.history
    seen = Counter(history)
    lost = sum(1 for n in range(1, COUNT + 1) if n not in seen)
    duplicated = sum(c - 1 for c in seen.values() if c > 1)
    states = [e.get('new') for e in result.events if e['kind'] == 'state']
    gaps = seq_ranges([n for n in range(1, COUNT + 1) if n not in seen], sep=',')
    covered = sum(int(r.get('crashes', 1)) for r in result.recoveries)
    return Outcome(case, history == list(range(1, COUNT + 1)), lost, duplicated,
                   'FATAL' in states, len(result.recoveries), missing=gaps,
                   strikes=len(result.kills), covered=covered)


def scenario(kills: tuple[Kill, ...], workdir: Path, domain_id: int) -> ScenarioResult:
    """The campaign's run with these strikes (none: a run without a fault, as the load
    campaign makes); raises RuntimeError when the harness fails."""
    return run('rory', kills, workdir, domain_id=domain_id, count=COUNT, rate=RATE,
               interval=1.0, pace='fast', program=FLAKY, timeout=90.0)


def run_case(case: Case, workdir: Path, domain_id: int) -> Outcome:
    """One run, in its own folder and ROS domain; a harness failure is an outcome too."""
    try:
        result = scenario(case.kills(), workdir, domain_id)
    except RuntimeError as err:
        return Outcome(case, False, COUNT, 0, True, 0, str(err).splitlines()[0])
    return judge(case, result)


def table(outcomes: Sequence[Outcome]) -> str:
    """Markdown table: per fault kind, and the total."""
    lines = ['| fault | runs | correct | lost | applied twice | give-ups | recoveries |',
             '|---|---:|---:|---:|---:|---:|---:|']

    def row(name: str, group: Sequence[Outcome]) -> str:
        return (f'| {name} | {len(group)} | {sum(o.correct for o in group)} '
                f'| {sum(o.lost for o in group)} | {sum(o.duplicated for o in group)} '
                f'| {sum(o.gave_up for o in group)} | {sum(o.recoveries for o in group)} |')

    for fault in FAULTS:
        group = [o for o in outcomes if o.case.fault == fault]
        if group:
            lines.append(row(fault, group))
    doubles = [o for o in outcomes if o.case.second is not None]
    if doubles:
        lines.append(row('(of which: second strike during recovery)', doubles))
    lines.append(row('**all**', outcomes))
    return '\n'.join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the campaign; exit 1 unless every run recovered exactly."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.faults.fault_campaign',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--short', action='store_true', help='the CI version (7 runs)')
    parser.add_argument('--runs', type=int, default=8, help='runs per fault (full campaign)')
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--domain', type=int, default=90, help='ROS domain id to use')
    parser.add_argument('--out', help='keep the runs here (default: a temporary folder)')
    args = parser.parse_args(argv)
    cases = short_plan() if args.short else plan(args.runs, args.seed)
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-faults-'))
    outcomes = []
    for i, case in enumerate(cases):
        outcome = run_case(case, root / f'run{i:03d}', args.domain)
        outcomes.append(outcome)
        verdict = 'ok' if outcome.correct else (
            f'WRONG: lost {outcome.lost} ({outcome.missing}), twice {outcome.duplicated}'
            f'{", gave up" if outcome.gave_up else ""} {outcome.error} '
            f'-> {root / f"run{i:03d}"}')
        print(f'[{i + 1}/{len(cases)}] {case.label()}: {verdict}', flush=True)
    print()
    print(table(outcomes))
    if not args.out and all(o.correct for o in outcomes):
        shutil.rmtree(root, ignore_errors=True)  # kept when a run went wrong
    return 0 if all(o.correct for o in outcomes) else 1


if __name__ == '__main__':
    sys.exit(main())
