"""``make faults``, part two: the real targets in the simulator, struck by every kind of fault.

For each target x world the target runs under RORY twice or more: once without a fault (the
reference) and once per fault kind at a random sim time - SIGKILL, SIGSEGV, an uncaught
exception in a callback, a callback that hangs (found by the heartbeat) - and once more with a
second strike of a random kind soon after the replacement is spawned, i.e. during its recovery.
The targets run unchanged under ``python -m rory_eval.faults.flaky.inject`` (which wraps their
subscription callbacks behind one-shot flag files) with the simulator's internal driver, so a
run's inputs are identical to the reference's and a target's outputs are a deterministic
function of them: a recovery that loses nothing and applies nothing twice leaves every pose the
target publishes after its release byte for byte the reference's.

A run is correct when every output it shares with the reference is identical, none after the
release is missing, and the node did not give up. The table counts per fault: runs, correct
recoveries, outputs missing after the release (a lost message shows as a later difference or a
gap), outputs that differ (a message lost or applied twice changes every later pose of a SLAM
or localizer), input messages reported lost (``input_gap``), give-ups.

    python -m rory_eval.faults.target_faults                     # 5 targets x 3 worlds (~40 min)
    python -m rory_eval.faults.target_faults --targets grid_slam --worlds office_small
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import sys
import threading
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rory_eval.faults.flaky.inject import HANG_FLAG, RAISE_FLAG
from rory_eval.faults.target_crash import Comparison, compare, instrument, run_supervised
from rory_eval.harness.simrun import REPO, exit_on_sigterm, store_events, wait_for_clock
from rory_eval.targets import EXACT_TARGETS, POSE_STAMPED, Target

FAULTS = ('SIGKILL', 'SIGSEGV', 'raise', 'hang')
WORLDS = ('office_small', 'workshop', 'real_room')
DURATION = 16.0  # sim seconds per run
HANG_TIMEOUT = 3.0  # s: a callback blocked this long is hung (graph_slam's optimisation < 1 s)
CLOCK_TIMEOUT = 90.0


@dataclass(frozen=True)
class Case:
    """One faulted run."""

    target: str
    world: str
    fault: str
    at: float  # sim seconds
    second: tuple[str, float] | None = None  # (fault, seconds after the replacement's spawn)

    def label(self) -> str:
        """Short description."""
        again = '' if self.second is None else (
            f', then {self.second[0]} {self.second[1]:.2f} s after the respawn')
        return f'{self.target}/{self.world}: {self.fault} at {self.at:.1f} s{again}'


@dataclass
class Outcome:
    """What one faulted run showed against its reference."""

    case: Case
    comparison: Comparison | None
    strikes: int = 0
    recoveries: int = 0
    input_gaps: int = 0  # input messages reported never to have reached the host
    gave_up: bool = False
    error: str = ''

    @property
    def correct(self) -> bool:
        """Exact outputs after the recovery, no give-up, every strike made."""
        expected = 1 if self.case.second is None else 2
        return (not self.error and not self.gave_up and self.comparison is not None
                and self.comparison.exact and self.strikes == expected
                and self.recoveries >= 1)

    @property
    def differing(self) -> int:
        """Outputs at a shared stamp that differ from the reference."""
        c = self.comparison
        return 0 if c is None else c.common - c.identical


def plan(targets: Sequence[str], worlds: Sequence[str], seed: int = 0) -> list[Case]:
    """Every fault once per target x world, plus one double strike; random, seeded times."""
    rng = random.Random(seed)
    cases = []
    for target in targets:
        for world in worlds:
            for fault in FAULTS:
                cases.append(Case(target, world, fault, round(rng.uniform(3.0, 10.0), 2)))
            # The first strike early enough that two hangs (hang_timeout each), a backoff and
            # the recovery fit in the run: a run that ends mid-recovery shows nothing.
            cases.append(Case(target, world, rng.choice(FAULTS), round(rng.uniform(3.0, 5.0), 2),
                              (rng.choice(FAULTS), round(rng.uniform(0.2, 1.0), 2))))
    return cases


class _Striker(threading.Thread):
    """Delivers a case's faults: signals to the node's pid, flags into its working folder."""

    def __init__(self, case: Case, sim_log: Path, world: str, folder: Path, store: Path) -> None:
        super().__init__(daemon=True, name='striker')
        self.case, self.sim_log, self.world = case, sim_log, world
        self.folder, self.store = folder, store
        self.strikes = 0
        self.error = ''
        self._finish = threading.Event()

    def _spawns(self) -> list[dict[str, Any]]:
        return [e for e in store_events(self.store) if e['kind'] == 'spawn']

    def _strike(self, fault: str) -> bool:
        if fault in ('raise', 'hang'):
            (self.folder / (RAISE_FLAG if fault == 'raise' else HANG_FLAG)).touch()
        else:
            spawns = self._spawns()
            if not spawns:
                self.error = 'the node was never spawned'
                return False
            try:
                os.kill(int(spawns[-1]['pid']), signal.Signals[fault])
            except ProcessLookupError:
                self.error = f'{fault}: pid {spawns[-1]["pid"]} was already gone'
                return False
        self.strikes += 1
        return True

    def run(self) -> None:
        if not wait_for_clock(self.sim_log, self.world, self._finish, CLOCK_TIMEOUT):
            self.error = 'the clock never started'
            return
        if self._finish.wait(self.case.at):
            self.error = 'the run ended before the strike'
            return
        spawned = len(self._spawns())
        if not self._strike(self.case.fault) or self.case.second is None:
            return
        fault, after = self.case.second
        # The replacement: a spawn record beyond those before the first strike.
        while len(self._spawns()) <= spawned:
            if self._finish.wait(0.01):
                self.error = 'the node was not respawned before the run ended'
                return
        if self._finish.wait(after):
            self.error = 'the run ended before the second strike'
            return
        self._strike(fault)

    def stop(self) -> None:
        self._finish.set()
        self.join(timeout=2.0)


def run_target(target: Target, world: str, out: Path, *, domain_id: int,
               case: Case | None = None, duration: float = DURATION,
               instrumented: Path | None = None) -> tuple[dict[int, bytes], list[dict[str, Any]],
                                                          _Striker | None]:
    """One run under RORY with the fault injector; pose messages by stamp, events, striker."""
    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    inst = instrument(target, instrumented or out / 'inst')
    store = out / 'store'
    # A store left by an earlier campaign in the same folder would be recovered from (that is
    # what a store is for): every run starts from none.
    for old in (store, out / 'run'):
        shutil.rmtree(old, ignore_errors=True)
    for flag in (RAISE_FLAG, HANG_FLAG):
        (out / flag).unlink(missing_ok=True)
    command = ['python', '-m', 'rory_eval.faults.flaky.inject', str(inst / target.node_file),
               *target.argv(world)[2:]]
    settings = {'hang_timeout': HANG_TIMEOUT,
                # rory_eval must be importable from the node's folder (out/).
                'env': {'PYTHONPATH': str(REPO)}}
    striker = None
    if case is not None:
        striker = _Striker(case, out / 'run' / 'sim.log', world, out, store)
    by_stamp, events = run_supervised(target, world, out, domain_id=domain_id, duration=duration,
                                      command=command, settings=settings, fault=striker)
    return by_stamp, events, striker


def run_case(case: Case, reference: dict[int, bytes], out: Path, *, domain_id: int,
             instrumented: Path | None = None) -> Outcome:
    """One faulted run, judged against the reference."""
    try:
        crashed, events, striker = run_target(EXACT_TARGETS[case.target], case.world, out,
                                              domain_id=domain_id, case=case,
                                              instrumented=instrumented)
    except Exception as err:  # the run failed to run: reported in the table
        return Outcome(case, None, error=f'{type(err).__name__}: {err}')
    assert striker is not None
    comparison = compare(reference, crashed, events)
    if not comparison.exact:
        write_differences(reference, crashed, EXACT_TARGETS[case.target], out / 'differences.txt')
    return Outcome(
        case, comparison, strikes=striker.strikes,
        recoveries=sum(e['kind'] == 'recovered' for e in events),
        input_gaps=sum(int(e['missing']) for e in events if e['kind'] == 'input_gap'),
        gave_up=any(e['kind'] == 'state' and e.get('new') == 'FATAL' for e in events),
        error=striker.error)


def _flatten(msg: Any, prefix: str = '') -> dict[str, Any]:
    """A message's leaf fields by dotted path (arrays indexed), for a field-by-field diff."""
    fields = getattr(msg, 'get_fields_and_field_types', None)
    if fields is None:
        if isinstance(msg, (list, tuple)) or hasattr(msg, 'tolist'):
            items = msg.tolist() if hasattr(msg, 'tolist') else list(msg)
            out: dict[str, Any] = {}
            for k, item in enumerate(items):
                out.update(_flatten(item, f'{prefix}[{k}]'))
            return out
        return {prefix: msg}
    out = {}
    for name in fields():
        out.update(_flatten(getattr(msg, name), f'{prefix}.{name}' if prefix else name))
    return out


def write_differences(reference: dict[int, bytes], crashed: dict[int, bytes], target: Target,
                      path: Path) -> None:
    """The evidence a wrong run leaves beside its store and logs (``run/supervisor.log`` has the
    node's output): per stamp whose output differs or is missing, the fields that differ with
    both values at full precision; and both runs' outputs as CDR (hex) in ``outputs.json``."""
    from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
    from rclpy.serialization import deserialize_message

    msg_type = PoseStamped if target.pose_type == POSE_STAMPED else PoseWithCovarianceStamped
    lines = ['stamp_s | field: reference -> crashed']
    for stamp in sorted(set(reference) | set(crashed)):
        ref, got = reference.get(stamp), crashed.get(stamp)
        if ref == got:
            continue
        if ref is None or got is None:
            lines.append(f'{stamp / 1e9:.3f} | {"reference" if ref is None else "crashed"} '
                         'has none')
            continue
        a = _flatten(deserialize_message(ref, msg_type))
        b = _flatten(deserialize_message(got, msg_type))
        changed = [f'{k}: {a.get(k)!r} -> {b.get(k)!r}' for k in a if a.get(k) != b.get(k)]
        lines.append(f'{stamp / 1e9:.3f} | ' + ('; '.join(changed) or 'bytes differ, fields equal'))
    path.write_text('\n'.join(lines) + '\n')
    (path.parent / 'outputs.json').write_text(json.dumps({
        'reference': {str(k): v.hex() for k, v in sorted(reference.items())},
        'crashed': {str(k): v.hex() for k, v in sorted(crashed.items())},
    }))


@dataclass
class _Row:
    runs: int = 0
    correct: int = 0
    missing: int = 0
    differing: int = 0
    gaps: int = 0
    gave_up: int = 0
    notes: list[str] = field(default_factory=list)


def table(outcomes: Sequence[Outcome]) -> str:
    """The campaign's Markdown table, one row per fault kind (double strikes apart)."""
    rows: dict[str, _Row] = {}
    for o in outcomes:
        key = o.case.fault if o.case.second is None else 'second strike during recovery'
        row = rows.setdefault(key, _Row())
        row.runs += 1
        row.correct += o.correct
        row.missing += 0 if o.comparison is None else o.comparison.missing_after_release
        row.differing += o.differing
        row.gaps += o.input_gaps
        row.gave_up += o.gave_up
        if not o.correct:
            row.notes.append(f'{o.case.label()}: {o.error or o.comparison}')
    lines = ['| fault | runs | correct | outputs missing | outputs differing | '
             'input messages lost | give-ups |', '|---|---:|---:|---:|---:|---:|---:|']
    for key, r in rows.items():
        lines.append(f'| {key} | {r.runs} | {r.correct} | {r.missing} | {r.differing} | '
                     f'{r.gaps} | {r.gave_up} |')
    total = _Row()
    for r in rows.values():
        total.runs += r.runs
        total.correct += r.correct
    lines.append(f'| **all** | {total.runs} | {total.correct} | | | | |')
    notes = [n for r in rows.values() for n in r.notes]
    return '\n'.join(lines + ([''] + [f'- {n}' for n in notes] if notes else []))


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        msg = f'{value} is not 1 or more'
        raise argparse.ArgumentTypeError(msg)
    return value


def main(argv: Sequence[str] | None = None) -> int:
    """Run the campaign; print the table; exit 0 when every run was correct."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.faults.target_faults',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--targets', nargs='+', default=sorted(EXACT_TARGETS),
                        choices=sorted(EXACT_TARGETS))
    parser.add_argument('--worlds', nargs='+', default=list(WORLDS), choices=WORLDS)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--domain', type=int, default=96)
    parser.add_argument('--out', type=Path, default=Path('faults-out'))
    parser.add_argument('--only', choices=('single', 'double'),
                        help='only the single-strike or only the double-strike cases')
    parser.add_argument('--strike', nargs=2, metavar=('FAULT', 'AT'),
                        help='instead of the seeded plan: this fault at AT sim seconds, on each '
                             'target x world')
    parser.add_argument('--then', nargs=2, metavar=('FAULT', 'AFTER'),
                        help='with --strike: a second fault AFTER seconds after the respawn')
    parser.add_argument('--repeat', type=_positive_int, default=1, metavar='N',
                        help='run each case N times (to chase a rare wrong run)')
    args = parser.parse_args(argv)
    if args.then is not None and args.strike is None:
        parser.error('--then needs --strike')
    for given in (args.strike, args.then):
        if given is not None and given[0] not in FAULTS:
            parser.error(f'unknown fault {given[0]!r}; one of {", ".join(FAULTS)}')
    times = {}
    for option, given in (('--strike', args.strike), ('--then', args.then)):
        if given is not None:
            try:
                times[option] = float(given[1])
            except ValueError:
                parser.error(f'{option} {given[0]} {given[1]}: {given[1]!r} is not seconds')
            if not times[option] >= 0.0:
                parser.error(f'{option} {given[0]} {given[1]}: seconds must be 0 or more')
    if args.strike is not None:
        second = None if args.then is None else (args.then[0], times['--then'])
        cases = [Case(t, w, args.strike[0], times['--strike'], second)
                 for t in args.targets for w in args.worlds]
    else:
        cases = plan(args.targets, args.worlds, args.seed)
    if args.only is not None:
        cases = [c for c in cases if (c.second is None) == (args.only == 'single')]
    cases = [c for c in cases for _ in range(args.repeat)]
    exit_on_sigterm()
    started = time.monotonic()
    outcomes: list[Outcome] = []
    references: dict[tuple[str, str], dict[int, bytes]] = {}
    for k, case in enumerate(cases, 1):
        key = (case.target, case.world)
        inst = args.out.resolve() / case.target / 'inst'
        if key not in references:
            references[key], _, _ = run_target(
                EXACT_TARGETS[case.target], case.world, args.out / case.target / case.world / 'ref',
                domain_id=args.domain, instrumented=inst)
        outcome = run_case(case, references[key],
                           args.out / case.target / case.world / f'case{k}',
                           domain_id=args.domain, instrumented=inst)
        outcomes.append(outcome)
        print(f'[{k}/{len(cases)}] {case.label()}: '
              f'{"correct" if outcome.correct else "WRONG"} '
              f'({outcome.recoveries} recoveries, {outcome.strikes} strikes'
              f'{", " + outcome.error if outcome.error else ""})', flush=True)
    print()
    print(table(outcomes))
    counts = Counter(o.correct for o in outcomes)
    print(f'\n{counts[True]}/{len(outcomes)} correct in {(time.monotonic() - started) / 60:.1f} '
          'min')
    return 0 if counts[False] == 0 else 1


if __name__ == '__main__':
    sys.exit(main())
