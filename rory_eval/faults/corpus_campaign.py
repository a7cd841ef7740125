"""``make faults``, every input: each corpus node, fast replay, SIGKILLed at random times.

The corpus (``tests/integration/corpus``) is node code as people write it: nine styles of
subscription-driven nodes, and six whose state depends on more than their messages - a node that
measures ``dt`` with its clock, one that works in a timer, one whose 1 Hz timer samples what it
counted (its ticks must stay on their grid), one tuned by a parameter at run time, one commanded
through a service, and a lifecycle node managed through ``~/change_state`` (those last three
driven by ``corpus/operator.py``, acting when it sees given numbers go by). Each node runs once
without a crash (its reference) and once per kill, with ``fast`` replay, SIGKILLed a random time
into its numbers (1..200 at 50 Hz; 1..300 for the three an operator drives,
:data:`OPERATED_COUNT`).

A crashed run is judged against its reference (:data:`NODES`, ``judge``):

* the nine styles: the final state equals the reference's exactly;
* the six others read times or take requests whose moment differs from run to run, so the
  parts that do not are compared exactly (the numbers applied, their sums, the sequence of
  gains, modes and lifecycle states they were counted under), and the rest is checked for
  what replay must keep: the state is what the node's own recorded readings imply, no clock
  reading or tick lags by the time since the checkpoint (what a replay on live time shows).

    python -m rory_eval.faults.corpus_campaign --kills 3       # ~10 min here
"""

from __future__ import annotations

import argparse
import itertools
import random
import shutil
import sys
import tempfile
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rory_eval.harness.scenario import (
    Kill,
    Program,
    ScenarioResult,
    child_process,
    run,
    scenario_env,
)
from rory_eval.harness.simrun import exit_on_sigterm

CORPUS = Path(__file__).resolve().parents[2] / 'tests' / 'integration' / 'corpus'
COUNT = 200  # 4 s at 50 Hz
OPERATED_COUNT = 300
"""The stream of a node an operator drives (6 s at 50 Hz). Its steps wait for the node's first
checkpoint (corpus/operator.py), and a kill just before that checkpoint puts it a checkpoint
interval later (a recovered node's schedule starts at its release): 2 s after the release that
follows the crash, ~4.2 s into the numbers, after which the steps still need their numbers. In
200 numbers the last step could fall after the last number (a run of 2026-11-28 killed at 1.42
s lost its lifecycle node's last transition that way)."""
# What a message's clock reading or a tick may lag in a recovered run beyond the recovery's
# own time (crash detected -> released): a tick period and the handover. A replay on live time
# shows the time since the checkpoint on top of the recovery.
LAG_SLACK_NS = 500_000_000

State = Any  # the node's last /state, decoded from JSON
# (the reference run's state or None, the crashed run's, the lag allowed in ns) -> problems
Judge = Callable[[State | None, State, int], list[str]]


def _numbers(state: State, expected: int = COUNT) -> list[str]:
    count = state.get('count')
    return [] if count == expected else [f'count {count}, expected {expected}']


def same_state(reference: State | None, crashed: State, _lag: int) -> list[str]:
    """A deterministic node: the crashed run ends exactly where the reference does (without a
    reference there is nothing to compare)."""
    if reference is None:
        return []
    return [] if crashed == reference else ['final state differs from the no-crash run']


def clock_integrator(reference: State | None, crashed: State, lag: int) -> list[str]:
    """``dt`` from the node's clock: every number once, the position its own readings imply,
    no reading lagging its message by more than the outage."""
    problems = _numbers(crashed)
    numbers = [n for n, _ in crashed['readings']]
    if numbers != list(range(1, COUNT + 1)):
        problems.append('numbers not applied exactly once, in order')
    if crashed['total'] != COUNT * (COUNT + 1) // 2 or (
            reference is not None and crashed['total'] != reference['total']):
        problems.append(f'total {crashed["total"]}')
    position, last = 0.0, None
    for n, now_ns in crashed['readings']:
        if last is not None:
            position += n * (now_ns - last) / 1e9
        last = now_ns
    if crashed['position'] != position:
        problems.append('position is not what its clock readings imply')
    times = [t for _, t in crashed['readings']]
    if times != sorted(times):
        problems.append('clock readings go backwards')
    if crashed['max_lag_ns'] >= lag:
        problems.append(f'a reading lags its message by {crashed["max_lag_ns"] / 1e9:.2f} s')
    return problems


def timer_mapper(reference: State | None, crashed: State, lag: int) -> list[str]:
    """Work in a timer: every number in exactly one batch or pending, every tick once, no gap
    between ticks longer than the outage."""
    problems = _numbers(crashed)
    covered = [n for batch in crashed['batches'] for n in batch] + crashed['pending']
    if covered != list(range(1, COUNT + 1)):
        problems.append('numbers not integrated exactly once, in order')
    gaps = [b - a for a, b in itertools.pairwise(crashed['tick_ns'])]
    if gaps and min(gaps) <= 0:
        problems.append('a tick repeated or out of order')
    if gaps and max(gaps) >= lag:
        problems.append(f'ticks {max(gaps) / 1e9:.2f} s apart (a tick lost)')
    return problems


# How late a tick may run on a busy machine (an executor's lateness); the one tick due while
# the node was down fires at release, later.
TICK_LATE_NS = 60_000_000


def sampler_grid(state: State, count: int = COUNT) -> list[str]:
    """A 1 Hz timer sampling what the node counted (corpus/sampler.py), as a run without a
    crash shows it: every number once; each tick saw exactly the numbers applied before it (by
    the node's own clock); one tick per second on the grid of the first, none skipped or twice,
    each on time but for at most one (a tick due while the node was down fires once at
    release, as in a stalled executor)."""
    problems = [] if state.get('count') == count else [
        f"count {state.get('count')}, expected {count}"]
    seen, samples = state['seen_ns'], state['samples']
    if seen != sorted(seen):
        problems.append('numbers applied out of clock order')
    for at, saw in samples:
        before = sum(1 for s in seen if s <= at)
        if before != saw:
            problems.append(f'the tick at {at} saw {saw} numbers; {before} came before it')
    if not samples:
        return [*problems, 'no tick']
    first = samples[0][0]
    slots = [int((at - first + TICK_LATE_NS) // 1_000_000_000) for at, _ in samples]
    if slots != list(range(len(slots))):
        problems.append(f'ticks not one per second on the grid: slots {slots}')
    late = [at - first - slot * 1_000_000_000 for (at, _), slot in zip(samples, slots, strict=True)]
    if sum(1 for ns in late if ns > TICK_LATE_NS) > 1:
        problems.append(f'ticks off the grid by {[round(ns / 1e6) for ns in late]} ms')
    return problems


def sampler(_reference: State | None, crashed: State, _lag: int) -> list[str]:
    """The sampler's run, judged on its own grid (:func:`sampler_grid`)."""
    return sampler_grid(crashed)


def _runs(field: str, total: str, count: int = OPERATED_COUNT) -> Judge:
    """A node counting under a setting changed from outside (``count`` numbers): the settings
    in the order the reference had them, and the total those runs imply."""

    def judge(reference: State | None, crashed: State, _lag: int) -> list[str]:
        problems = _numbers(crashed, count)
        settings = [setting for setting, _ in crashed[field]]
        if reference is not None and settings != [s for s, _ in reference[field]]:
            problems.append(f'{field} {crashed[field]}, the no-crash run had {reference[field]}')
        implied, n = 0.0, 0
        for setting, how_many in crashed[field]:
            for _ in range(how_many):
                n += 1
                implied += setting * n
        if crashed[total] != implied or n != count:
            problems.append(f'{total} {crashed[total]} is not what its {field} imply')
        return problems

    return judge


@dataclass(frozen=True)
class CorpusNode:
    """One corpus node, how to drive it and how to judge a crashed run of it."""

    file: str
    name: str
    judge: Judge
    operator: tuple[str, ...] = ()  # corpus/operator.py's arguments, if it needs an operator
    count: int = COUNT  # numbers in its stream

    def program(self) -> Program:
        return Program(CORPUS, CORPUS / 'keyvars.yaml', self.file, '/state', self.name)


NODES: tuple[CorpusNode, ...] = (
    CorpusNode('closures.py', 'closures', same_state),
    CorpusNode('functional.py', 'functional', same_state),
    CorpusNode('dataclass_state.py', 'dataclasses', same_state),
    CorpusNode('enum_machine.py', 'enum_machine', same_state),
    CorpusNode('numpy_state.py', 'numpy', same_state),
    CorpusNode('message_list.py', 'message_list', same_state),
    CorpusNode('helper_objects.py', 'helper_objects', same_state),
    CorpusNode('kwargs_sub.py', 'keyword_subscription', same_state),
    CorpusNode('derived.py', 'derived_with_time', same_state),
    CorpusNode('clock_integrator.py', 'clock_integrator', clock_integrator),
    CorpusNode('timer_mapper.py', 'timer_mapper', timer_mapper),
    CorpusNode('sampler.py', 'sampler', sampler),
    CorpusNode('gain_controller.py', 'gain_controller', _runs('gains', 'total'),
               ('gain', '20=2.0', 'c10=3.0'), OPERATED_COUNT),
    CorpusNode('mode_switch.py', 'mode_switch', _runs('runs', 'total'),
               ('fast', '20=1', 'c10=0'), OPERATED_COUNT),
    CorpusNode('lifecycle_counter.py', 'lifecycle_counter', _runs('runs', 'total'),
               ('lifecycle', '0=configure', '30=activate', 'c5=deactivate', 'c15=activate'),
               OPERATED_COUNT),
)


def run_node(node: CorpusNode, kills: tuple[Kill, ...], workdir: Path,
             domain: int) -> ScenarioResult:
    """One run of ``node`` (its operator too, if it has one); every process is reaped."""
    workdir.mkdir(parents=True, exist_ok=True)
    with ExitStack() as stack:
        if node.operator:
            stack.enter_context(child_process(
                [sys.executable, str(CORPUS / 'operator.py'), *node.operator],
                scenario_env(domain), workdir, workdir / 'operator.log'))
        # fast whatever keyvars.yaml says (one corpus node asks for paced, to test that)
        return run('rory', kills, workdir, domain_id=domain, count=node.count, interval=None,
                   pace='fast', program=node.program(),
                   other_readers=1 if node.operator else 0)


def judge_run(node: CorpusNode, reference: State | None, result: ScenarioResult) -> list[str]:
    """What is wrong with a crashed run of ``node`` (nothing: it recovered exactly)."""
    state = result.state
    if state is None:
        return ['the node published no state']
    recovery_ns = max((int(r['total_ms'] * 1e6) for r in result.recoveries), default=0)
    problems = node.judge(reference, state, recovery_ns + LAG_SLACK_NS)
    if len(result.recoveries) != len(result.kills):
        problems.append(f'{len(result.recoveries)} recoveries for {len(result.kills)} kills')
    problems += [f'replayed {r["replay"]}' for r in result.recoveries if r['replay'] != 'fast']
    return problems


def kill_times(seed: int, node: str, kills: int) -> list[float]:
    """Seconds into the numbers to kill ``node`` at, drawn uniformly over the stream from the
    seed and the node's name: a node added to the corpus, or left out with ``--nodes``, does
    not move the others' kills."""
    rng = random.Random(f'{seed}/{node}')
    return [round(rng.uniform(0.2, 3.6), 2) for _ in range(kills)]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the campaign; exit 1 unless every crashed run was judged exact."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.faults.corpus_campaign',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--kills', type=int, default=3, help='kill times per node')
    parser.add_argument('--seed', type=int, default=23)
    parser.add_argument('--nodes', nargs='+', choices=[n.name for n in NODES],
                        help='only these nodes')
    parser.add_argument('--domain', type=int, default=93, help='ROS domain id to use')
    parser.add_argument('--out', help='keep the runs here (default: a temporary folder)')
    args = parser.parse_args(argv)
    if args.kills < 1:
        parser.error('--kills must be at least 1')
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-corpus-'))
    rows: list[tuple[str, int, int]] = []
    for node in (n for n in NODES if not args.nodes or n.name in args.nodes):
        reference = run_node(node, (), root / node.name / 'reference', args.domain)
        ref_state = reference.state
        problems_ref = (['no state'] if ref_state is None
                        else node.judge(None, ref_state, LAG_SLACK_NS))
        if problems_ref:
            print(f'{node.name}: the no-crash run itself is wrong: {problems_ref}', flush=True)
        exact = 0
        for i, at in enumerate(kill_times(args.seed, node.name, args.kills)):
            workdir = root / node.name / f'kill{i}'
            result = run_node(node, (Kill(after=at),), workdir, args.domain)
            problems = judge_run(node, ref_state, result)
            exact += not problems
            print(f'{node.name}: SIGKILL at {at:.2f} s: '
                  f'{"exact" if not problems else "; ".join(problems) + f" -> {workdir}"}',
                  flush=True)
            if not problems and not args.out:
                shutil.rmtree(workdir, ignore_errors=True)
        rows.append((node.name, args.kills, exact))
    print()
    print('| node | kills | exact |')
    print('|---|---:|---:|')
    for name, kills, exact in rows:
        print(f'| {name} | {kills} | {exact} |')
    total = sum(k for _, k, _ in rows)
    exact_total = sum(e for _, _, e in rows)
    print(f'| all | {total} | {exact_total} |')
    ok = exact_total == total
    if ok and not args.out:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
