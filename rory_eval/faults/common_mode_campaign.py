"""``make faults``, common mode: one message that every reader of a topic dies on (issue 38).

A malformed message on a shared topic takes down every node that reads it at the same moment.
Each run here: three instrumented integrators (``rory_eval/faults/poisoned``: each raises on
the number its ``poison`` parameter names, every time) read /numbers under one ``rory
supervise``; a publisher sends 1..N at 50 Hz (its sequence number is the number it sends). All
three crash on the poison number live, recover, crash again when their replay reaches it, and
must come back with it quarantined.

A run is exact when, for every node: its final history is 1..N without the poison number, in
order, nothing twice; it crashed twice (two ``exit`` events) and never gave up; its one
``recovered`` event covers both crashes and names the message (``died_on`` and
``quarantined``: topic, source stamp, sequence number); its quarantine folder holds one record,
of that message.

    python -m rory_eval.faults.common_mode_campaign --runs 3
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rory_eval.harness.scenario import (
    EXAMPLE,
    EventsFile,
    EventTracker,
    Program,
    _Observer,
    child_process,
    joining,
    prepare,
    scenario_env,
)
from rory_eval.harness.simrun import exit_on_sigterm

POISONED_DIR = Path(__file__).resolve().parent / 'poisoned'
POISONED = Program(POISONED_DIR, POISONED_DIR / 'keyvars.yaml', 'poisoned_integrator.py',
                   '/integrator/state', 'integrator')
NODES = ('left', 'middle', 'right')
TOPIC = '/numbers'
COUNT = 150  # 3 s at 50 Hz
RATE = 50.0
POISON = 40  # 0.8 s in: both crashes and recoveries come while numbers still arrive


def three_readers_config(workdir: Path, poison: int) -> Path:
    """The poisoned integrator three times in one supervisor config, each with its own node
    name and state topic, all raising on ``poison``; the config's path."""
    config_path = prepare(workdir, 'rory', interval=2.0, pace=None, program=POISONED)
    config: dict[str, Any] = yaml.safe_load(config_path.read_text())
    (node,) = config['nodes']
    config['nodes'] = [
        {**node, 'name': name,
         'command': [*node['command'], '--ros-args', '-r', f'__node:={name}',
                     '-r', f'/integrator/state:=/{name}/state', '-p', f'poison:={poison}']}
        for name in NODES
    ]
    config_path.write_text(yaml.safe_dump(config, sort_keys=False))
    return config_path


@dataclass
class CommonModeRun:
    """What one run produced."""

    count: int
    poison: int
    states: dict[str, Any]  # per node, its last published state
    events: list[dict[str, Any]] = field(repr=False)
    quarantine: dict[str, list[dict[str, Any]]]  # per node, its quarantine records
    seconds: float = 0.0  # supervisor start to the last node back with every number
    log_tail: str = field(repr=False, default='')

    def expected_history(self) -> list[int]:
        """What a run without a crash that skipped the poison number applies."""
        return [n for n in range(1, self.count + 1) if n != self.poison]


def _quarantine_records(store: Path, node: str) -> list[dict[str, Any]]:
    folder = store / node / 'quarantine'
    return [json.loads(p.read_text()) for p in sorted(folder.glob('*.json'))]


def _last_applied(state: Any) -> int | None:
    history = state.get('history') if isinstance(state, dict) else None
    return history[-1] if isinstance(history, list) and history else None


def run_common_mode(workdir: Path, domain_id: int, *, count: int = COUNT,
                    poison: int = POISON, rate: float = RATE,
                    timeout: float = 90.0) -> CommonModeRun:
    """One run in ``workdir`` and ROS domain ``domain_id``; reaps every process it started.

    Raises RuntimeError (its first line says what) when the nodes do not start, or do not all
    come back with the last number applied within ``timeout`` seconds.
    """
    workdir = workdir.resolve()
    config = three_readers_config(workdir, poison)
    store = workdir / 'store-rory'
    env = scenario_env(domain_id)
    with joining(domain_id):
        observers = {name: _Observer(domain_id, f'/{name}/state') for name in NODES}
    events = EventsFile(store / 'events.jsonl')
    trackers = {name: EventTracker() for name in NODES}
    sup_log = workdir / 'supervisor.log'
    started = time.monotonic()
    deadline = started + timeout

    def poll() -> None:
        for ev in events.poll():
            if ev.get('node') in trackers:
                trackers[ev['node']].feed([ev])

    def wait_until(what: str, done: Any) -> None:
        while not done():
            poll()
            if sup.poll() is not None:
                raise RuntimeError(f'the supervisor exited ({what}):\n'
                                   f'{sup_log.read_text()[-3000:]}')
            if time.monotonic() > deadline:
                raise RuntimeError(f'{what} within {timeout:g} s:\n{sup_log.read_text()[-3000:]}')
            time.sleep(0.01)

    def back_with_the_last_number() -> bool:
        return all(trackers[name].state == 'RUNNING'
                   and _last_applied(observers[name].state) == count for name in NODES)

    try:
        with child_process([sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
                           env, workdir, sup_log) as sup:
            wait_until('the nodes never ran',
                       lambda: all(t.state == 'RUNNING' for t in trackers.values()))
            # Three nodes and the ring's one reader for them all.
            publisher = [sys.executable, str(EXAMPLE / 'count_publisher.py'), str(count),
                         str(rate), str(len(NODES) + 1)]
            with child_process(publisher, env, workdir, workdir / 'publisher.log') as pub:
                wait_until('the publisher never finished', lambda: pub.poll() is not None)
                if pub.returncode != 0:
                    raise RuntimeError(f'the publisher failed:\n'
                                       f'{(workdir / "publisher.log").read_text()[-2000:]}')
                wait_until('the nodes never all came back with the last number',
                           back_with_the_last_number)
            seconds = time.monotonic() - started
    finally:
        for observer in observers.values():
            observer.close()
        events.poll()
    return CommonModeRun(
        count=count, poison=poison,
        states={name: observers[name].state for name in NODES},
        events=events.events,
        quarantine={name: _quarantine_records(store, name) for name in NODES},
        seconds=seconds,
        log_tail=sup_log.read_text()[-4000:],
    )


def _names_the_message(item: dict[str, Any], poison: int) -> bool:
    # The publisher's sequence number is the number it sent.
    return item.get('topic') == TOPIC and item.get('seq') == poison


def judge(run: CommonModeRun) -> dict[str, list[str]]:
    """Per node, what differs from the exact outcome (an empty list: exact)."""
    found: dict[str, list[str]] = {}
    for node in NODES:
        problems: list[str] = []
        mine = [e for e in run.events if e.get('node') == node]
        kinds = [e['kind'] for e in mine]
        history = run.states[node].get('history') if isinstance(run.states[node], dict) else None
        if history != run.expected_history():
            applied = history or []
            lost = sorted(set(run.expected_history()) - set(applied))
            twice = sorted(n for n in set(applied) if applied.count(n) > 1)
            problems.append(f'history not 1..{run.count} without {run.poison}: lost {lost}, '
                            f'twice {twice}, in order {applied == sorted(applied)}')
        if kinds.count('exit') != 2:
            problems.append(f'{kinds.count("exit")} crashes, not 2')
        if 'fatal' in kinds:
            problems.append('gave up')
        died_on = [e for e in mine if e['kind'] == 'died_on']
        if len(died_on) != 1 or not _names_the_message(died_on[0], run.poison):
            problems.append(f'the first crash is not put on the message: {died_on}')
        quarantined = [e for e in mine if e['kind'] == 'quarantined']
        if len(quarantined) != 1 or not _names_the_message(quarantined[0], run.poison):
            problems.append(f'quarantined events: {quarantined}')
        recovered = [e for e in mine if e['kind'] == 'recovered']
        if len(recovered) != 1 or recovered[0].get('crashes') != 2:
            problems.append('not one recovery of both crashes: '
                            f'{[(e.get("crashes"), e.get("incarnation")) for e in recovered]}')
        for event in recovered:
            named = event.get('died_on') or []
            if not named or not all(_names_the_message(m, run.poison) for m in named):
                problems.append(f'its recovered event does not name the message: died_on {named}')
            held = event.get('quarantined') or []
            if [_names_the_message(m, run.poison) for m in held] != [True]:
                problems.append(f'its recovered event does not name the quarantined message: '
                                f'{held}')
        records = run.quarantine[node]
        if len(records) != 1 or not _names_the_message(records[0], run.poison):
            named = [(r.get('topic'), r.get('seq')) for r in records]
            problems.append(f'quarantine records (topic, seq): {named}')
        found[node] = problems
    return found


def describe(run: CommonModeRun) -> str:
    """The verdict of one run, one line."""
    found = judge(run)
    if not any(found.values()):
        took = ', '.join(f'{e["node"]} {float(e["total_ms"]):.0f}' for e in run.events
                         if e['kind'] == 'recovered')
        return (f'exact: {len(NODES)} nodes crashed twice on {TOPIC} seq {run.poison}, came back '
                f'with it quarantined (recovered in ms: {took}; run {run.seconds:.1f} s)')
    wrong = '; '.join(f'{node}: {", ".join(p)}' for node, p in found.items() if p)
    return f'NOT EXACT: {wrong}'


def main(argv: Sequence[str] | None = None) -> int:
    """Run the scenario ``--runs`` times; exit 1 unless every run was exact."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.faults.common_mode_campaign',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--runs', type=int, default=3, help='runs of the scenario')
    parser.add_argument('--count', type=int, default=COUNT, help='numbers published')
    parser.add_argument('--poison', type=int, default=POISON,
                        help='the number every node raises on')
    parser.add_argument('--domain', type=int, default=93, help='ROS domain id to use')
    parser.add_argument('--out', help='keep the runs here (default: a temporary folder)')
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error('--runs must be at least 1')
    if not 1 <= args.poison < args.count:
        parser.error('--poison must be one of the numbers published, before the last')
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-common-mode-'))
    exact = 0
    for i in range(args.runs):
        workdir = root / f'run{i:03d}'
        try:
            run = run_common_mode(workdir, args.domain, count=args.count, poison=args.poison)
            verdict = describe(run)
            ok = not any(judge(run).values())
        except RuntimeError as err:
            verdict, ok = f'NOT EXACT: {str(err).splitlines()[0]}', False
        exact += ok
        print(f'[{i + 1}] {verdict}{"" if ok else f" -> {workdir}"}', flush=True)
        if ok and not args.out:
            shutil.rmtree(workdir, ignore_errors=True)
    print(f'{exact} of {args.runs} runs exact')
    if not args.out and exact == args.runs:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if exact == args.runs else 1


if __name__ == '__main__':
    sys.exit(main())
