"""``make faults``, idle: a node idle for minutes is never taken for hung (issue 36).

The heartbeat no longer comes from a timer in the node's executor: the ``rory-pulse`` thread
(rory_runtime/node/pulse.py) writes the beat itself while RORY's callbacks complete, and while none
does it posts a probe with ``Executor.create_task`` that beats when the executor runs it. A node
without inputs lives on those probes. This runs the example integrator under ``rory supervise``
(method rory) through the integrator harness, its numbers ``--minutes`` apart from each other
(``rate`` 1/60 Hz, ``minutes + 1`` numbers: idle for a minute between two), with a short
``hang_timeout`` (default 1 s): an idle node taken for hung would be killed many times over.

The integrator keeps its own 1 Hz state timer, which RORY runs as a tick (a callback that
counts as progress): between two numbers the executor wakes for it once a second and the
probes carry the other looks (four of the pulse's five a second). Its checkpoints (every 2 s of
the node's clock) are posted to the executor by the same thread.

The run is accepted (:func:`judge`, with the load campaign's judge of a run without a fault,
:meth:`load_campaign.RunRecord.failures`) when its supervisor's events show no ``hang`` and no
``unheard`` (no kill), no ``exit`` (no crash), no ``recovered``, no give-up, the safe state
never engaged (no ``held`` event, no ``True`` on ``/e_stop``), and the node's final history is
exactly 1..N. It prints one line per finding, then a summary; exit 0 when accepted, 1 when not
(the run's folder kept), 2 on bad arguments.

    python -m rory_eval.faults.idle_watch --minutes 3      # ~3 min
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rory_eval.faults.load_campaign import NO_CRASH, RunRecord, count_events, from_scenario
from rory_eval.harness.scenario import INTEGRATOR, Program, ScenarioResult, run
from rory_eval.harness.simrun import exit_on_sigterm

GAP_S = 60.0
"""Seconds between two numbers: the node is idle that long."""

CHECKPOINT_INTERVAL = 2.0
"""The node's checkpoint interval (the harness's): each one posted to the executor by the pulse."""

LATE_BEAT = re.compile(r'no heartbeat for ([0-9.]+) s: RORY keeps its inputs')
"""The supervisor's INFO line when a beat is late enough to keep the node's inputs
(``STALL_SUSPECT``, at most half of hang_timeout): not a kill, reported, not judged."""


@dataclass(frozen=True)
class Verdict:
    """What the run showed: ``notes`` say what was seen, ``failures`` why it is not accepted."""

    notes: list[str] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)

    @property
    def accepted(self) -> bool:
        """Nothing failed."""
        return not self.failures


def judge(result: ScenarioResult, hang_timeout: float) -> Verdict:
    """Judge a run of the idle integrator as a run without a fault (pure: reads ``result``)."""
    record = from_scenario(
        RunRecord('idle', NO_CRASH, 'idle integrator', Path('.'), False,
                  hang_limit=hang_timeout), result)
    record.exact, record.lost, record.twice = result.correct, result.lost, result.duplicated
    if not result.correct:
        record.problems.append(f'history {_brief(result.history)}, expected '
                               f'1..{result.expected}')
    counts = count_events(result.events)

    def n(kind: str) -> int:
        return sum(1 for e in result.events if e['kind'] == kind)

    late = [float(m.group(1)) for m in LATE_BEAT.finditer(result.log)]
    on = sum(1 for _, engaged in result.e_stop if engaged)
    notes = [
        f'final state: history {_brief(result.history)} (expected 1..{result.expected}), '
        f'{result.lost} lost, {result.duplicated} applied twice',
        f'kills: {n("hang")} hang, {n("unheard")} unheard',
        f'process exits: {counts.exits}; recoveries: {counts.recoveries}; '
        f'give-ups: {counts.give_ups}',
        f'safe state: {counts.held} held events, {on} True on /e_stop',
        f'checkpoints: {n("checkpoint")} taken, {n("checkpoints_overdue")} overdue warnings',
        'late heartbeats (inputs kept, not judged): '
        + (f'{len(late)}, the latest seen {max(late):.1f} s old' if late else '0'),
    ]
    return Verdict(notes, record.failures())


def _brief(history: list[int], most: int = 12) -> str:
    """A history short enough for one line."""
    if len(history) <= most:
        return str(history)
    shown = ', '.join(str(n) for n in history[:most - 2])
    return f'[{shown}, ..., {history[-1]}] ({len(history)} numbers)'


def idle_program(hang_timeout: float) -> Program:
    """The integrator with this ``hang_timeout`` in its supervisor config."""
    return Program(INTEGRATOR.source, INTEGRATOR.keyvars, INTEGRATOR.file,
                   INTEGRATOR.state_topic, INTEGRATOR.node,
                   settings=(*INTEGRATOR.settings, ('hang_timeout', hang_timeout)))


def scenario(minutes: int, hang_timeout: float, workdir: Path, domain: int) -> ScenarioResult:
    """``minutes + 1`` numbers, :data:`GAP_S` apart, to the integrator under ``rory
    supervise``; raises RuntimeError when the harness fails."""
    count = minutes + 1
    return run('rory', (), workdir, domain_id=domain, count=count, rate=1.0 / GAP_S,
               interval=CHECKPOINT_INTERVAL, program=idle_program(hang_timeout),
               timeout=minutes * GAP_S + 120.0)


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a whole number') from None
    if value < 1:
        raise argparse.ArgumentTypeError(f'{value} is less than 1')
    return value


def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r} is not a number') from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f'{text} is not more than 0')
    return value


def parser() -> argparse.ArgumentParser:
    """The command line."""
    p = argparse.ArgumentParser(prog='python -m rory_eval.faults.idle_watch',
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--minutes', type=_positive_int, default=3,
                   help='minutes of the run; one number a minute, minutes + 1 in all')
    p.add_argument('--hang-timeout', type=_positive_float, default=1.0, metavar='S',
                   help="the node's hang_timeout, seconds")
    # Below tests/conftest.py's domains (10 and up, per pytest worker) and beside the load
    # campaign's (5-8): a test session running meanwhile on 94 published its own numbers and
    # safe state into the first run of this watch.
    p.add_argument('--domain', type=int, default=9, help='ROS domain id to use')
    p.add_argument('--out', type=Path,
                   help='keep the run here (default: a temporary folder, kept if it fails)')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the idle integrator once; exit 0 when accepted, 1 when not."""
    exit_on_sigterm()
    args = parser().parse_args(argv)
    root = args.out if args.out else Path(tempfile.mkdtemp(prefix='rory-idle-'))
    count = args.minutes + 1
    print(f'idle watch: the integrator under rory supervise (method rory), {count} numbers '
          f'{GAP_S:g} s apart, hang_timeout {args.hang_timeout:g} s, domain {args.domain}',
          flush=True)
    started = time.monotonic()
    try:
        result = scenario(args.minutes, args.hang_timeout, root, args.domain)
    except RuntimeError as err:
        text = str(err).strip().splitlines()
        verdict = Verdict([], [f'did not run: {text[0] if text else "RuntimeError"}'])
    else:
        verdict = judge(result, args.hang_timeout)
    minutes = (time.monotonic() - started) / 60
    for line in verdict.notes:
        print(f'  {line}')
    for line in verdict.failures:
        print(f'  FAIL: {line}')
    if verdict.accepted:
        print(f'accepted: idle {GAP_S:g} s between {count} numbers for {minutes:.1f} min with '
              f'hang_timeout {args.hang_timeout:g} s: never taken for hung, no crash, no '
              'recovery, no safe state, final state exact')
        if not args.out:
            shutil.rmtree(root, ignore_errors=True)
        return 0
    print(f'NOT accepted ({minutes:.1f} min): {"; ".join(verdict.failures)} -> {root}')
    return 1


if __name__ == '__main__':
    sys.exit(main())
