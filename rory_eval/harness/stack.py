"""A whole stack under one supervisor in the simulator: AMCL localizes, the navigator drives on it.

One ``rory supervise`` config runs both nodes (each with its own method) and holds ``/e_stop``,
which the simulator obeys, while any of them recovers. The robot must reach the world's goal,
received once by the navigator (volatile, as from RViz), with no collision, however the nodes
are struck: one alone (the other keeps running, its process untouched) or several at the same
moment (all recover; the stop is held from the first one's S1 until the last one's S4).

    python -m rory_eval.harness.stack --world real_room --strike 8:amcl --strike 16:amcl,navigator

A strike is ``T:NODE[,NODE...]`` or ``T:all`` (:meth:`Strike.parse`): every node named is
SIGKILLed in one loop, microseconds apart, T sim seconds after the clock starts; ``all`` names
every node of the stack (here both; the six-target storm, ``rory_eval/faults/stack_storm.py``,
strikes its six with it).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rory_eval.harness.simrun import LATCHED, SimRun, store_events, wait_for_clock
from rory_eval.targets import TARGETS

NODES = ('amcl', 'navigator')
GOAL_XY = 0.25  # m, as the evaluation's judge (rory_eval/evaluation/judge.py)
CLOCK_TIMEOUT = 90.0


ALL = 'all'
"""A strike's node list that names every node of the stack."""


@dataclass(frozen=True)
class Strike:
    """SIGKILL these nodes ``at`` sim seconds after the clock starts, all at once."""

    at: float
    nodes: tuple[str, ...]

    @classmethod
    def parse(cls, text: str, among: Sequence[str] = NODES) -> Strike:
        """``T:NODE[,NODE...]`` or ``T:all``: ``8:amcl``, ``16:amcl,navigator``, ``12:all``.

        T is sim seconds (>= 0); each node is one of ``among``, the stack's nodes, at most
        once; ``all`` is every one of them, in their order. Raises ValueError naming what is
        wrong.
        """
        at, colon, names = text.partition(':')
        try:
            seconds = float(at)
        except ValueError:
            seconds = math.nan
        if not colon or not math.isfinite(seconds) or seconds < 0:
            msg = f'strike {text!r}: T:NODE[,NODE...] or T:all, T sim seconds >= 0'
            raise ValueError(msg)
        nodes = tuple(n.strip() for n in names.split(',') if n.strip())
        if nodes == (ALL,):
            nodes = tuple(among)
        unknown = [n for n in nodes if n not in among]
        if not nodes or unknown or len(set(nodes)) != len(nodes):
            msg = (f'strike {text!r}: name nodes among {", ".join(among)} (each once), '
                   f'or {ALL}')
            raise ValueError(msg)
        return cls(seconds, nodes)


@dataclass
class StackResult:
    """What one stack run showed."""

    world: str
    reached: bool  # the navigator said REACHED, and the robot is at the goal
    goal_distance: float
    collisions: int
    statuses: list[str]
    events: list[dict[str, Any]]
    strikes: list[tuple[float, str, int]]  # (wall time, node, pid killed)
    e_stop: list[tuple[float, bool]]  # (wall time received, data)
    errors: list[str] = field(default_factory=list)

    def spawns(self, node: str) -> list[dict[str, Any]]:
        """The node's spawn events, first start included."""
        return [e for e in self.events if e['kind'] == 'spawn' and e['node'] == node]

    def recoveries(self, node: str) -> list[dict[str, Any]]:
        """The node's 'recovered' events."""
        return [e for e in self.events if e['kind'] == 'recovered' and e['node'] == node]


def instrument(name: str, into: Path) -> Path:
    target = TARGETS[name]
    if not into.exists():
        subprocess.run([sys.executable, '-m', 'rory_instrument', str(target.folder), '--vars',
                        str(target.keyvars), '-o', str(into)], check=True,
                       capture_output=True)
    return into


def stack_config(world: str, out: Path, methods: dict[str, str]) -> Path:
    """The stack's ``rory supervise`` config: both nodes, /e_stop held while either recovers."""
    nodes = []
    for name in NODES:
        target = TARGETS[name]
        copy = instrument(name, out / 'inst' / name)
        # The instrumented copy's script, then the original's arguments (--ros-args, sim time,
        # the world's start pose, the map; the navigator's goal volatile, as from RViz).
        nodes.append({'name': name,
                      'command': ['python', str(copy / target.node_file),
                                  *target.argv(world)[2:]],
                      'method': methods.get(name, 'rory'), 'replay': 'fast'})
    config = {
        'nodes': nodes,
        'safe_state': [{'topic': '/e_stop', 'type': 'std_msgs/msg/Bool',
                        'hold': {'data': True}, 'release': {'data': False}}],
        'store': str(out / 'store'),
    }
    path = out / 'stack.yaml'
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


@contextlib.contextmanager
def first_in_line() -> Iterator[None]:
    """While a strike's kills are sent: this thread runs SCHED_FIFO where the system lets it
    (no other process's thread of the usual class takes its core) and keeps the GIL (no forced
    switch to this process's other threads); both as before afterwards. Under load, six kills
    sent from a plain thread were up to 13.6 ms apart (2026-11-28), not in the same
    millisecond."""
    interval = sys.getswitchinterval()
    before = None
    try:
        before = (os.sched_getscheduler(0), os.sched_getparam(0))
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except (OSError, AttributeError):
        before = None
    sys.setswitchinterval(1.0)
    try:
        yield
    finally:
        sys.setswitchinterval(interval)
        if before is not None:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, *before)


class Striker(threading.Thread):
    """Kills the named nodes at their sim times (the clock runs at wall pace).

    ``ready``, when given, is asked at each strike's time and then every 20 ms until it
    returns None (the stack has settled); until then it returns what is not ready yet, and a
    strike still waiting ``ready_timeout`` s after its time is not made (an error says why).
    ``struck_at`` holds, per strike made, its seconds after the clock started.
    """

    def __init__(self, sim_log: Path, world: str, store: Path,
                 strikes: Sequence[Strike], *,
                 ready: Callable[[], str | None] | None = None,
                 ready_timeout: float = 30.0) -> None:
        super().__init__(daemon=True, name='striker')
        self.sim_log, self.world, self.store = sim_log, world, store
        self.strikes = sorted(strikes, key=lambda s: s.at)
        self.ready, self.ready_timeout = ready, ready_timeout
        self.done: list[tuple[float, str, int]] = []
        self.struck_at: list[float] = []
        self.errors: list[str] = []
        self._finish = threading.Event()

    def _settled(self, strike: Strike) -> bool:
        """Wait for ``ready``; False (an error kept) when the run ended or it never was."""
        if self.ready is None:
            return True
        deadline = time.monotonic() + self.ready_timeout
        while (missing := self.ready()) is not None:
            if time.monotonic() > deadline:
                self.errors.append(f'not settled {self.ready_timeout:g} s after the strike at '
                                   f'{strike.at} s: {missing}')
                return False
            if self._finish.wait(0.02):
                self.errors.append(f'the run ended before the strike at {strike.at} s '
                                   f'({missing})')
                return False
        return True

    def run(self) -> None:
        if not wait_for_clock(self.sim_log, self.world, self._finish, CLOCK_TIMEOUT):
            self.errors.append('the clock never started')
            return
        start = time.monotonic()
        for strike in self.strikes:
            if self._finish.wait(max(0.0, start + strike.at - time.monotonic())):
                self.errors.append(f'the run ended before the strike at {strike.at} s')
                return
            if not self._settled(strike):
                return
            self.struck_at.append(time.monotonic() - start)
            spawns = store_events(self.store)
            pids = {}
            for node in strike.nodes:
                mine = [e for e in spawns if e['kind'] == 'spawn' and e['node'] == node]
                if not mine:
                    self.errors.append(f'{node} was never spawned')
                    continue
                pids[node] = int(mine[-1]['pid'])
            with first_in_line():
                sent = []
                for node, pid in pids.items():  # back to back: "at the same time"
                    try:
                        os.kill(pid, signal.SIGKILL)
                        sent.append((time.time(), node, pid))
                    except ProcessLookupError:
                        sent.append((math.nan, node, pid))
            for at, node, pid in sent:
                if math.isnan(at):
                    self.errors.append(f'{node} pid {pid} was already gone at {strike.at} s')
                else:
                    self.done.append((at, node, pid))

    def stop(self) -> None:
        self._finish.set()
        self.join(timeout=2.0)


def run_stack(world: str, out: Path, *, domain_id: int, strikes: Sequence[Strike],
              duration: float | None = None,
              methods: dict[str, str] | None = None,
              settle: float | None = None) -> StackResult:
    """One run of the stack; every process is reaped.

    ``settle``: end the run this many seconds after it is over (every strike struck, every
    struck node recovered, and then the navigator said REACHED), not at the end of its
    duration; None: run the whole duration.
    """
    from std_msgs.msg import Bool, String

    from rory_eval.harness.goals import goal_message
    from rory_eval.targets import NAVIGATION_SECONDS
    from sim.worlds import get_world

    out = out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    config = stack_config(world, out, methods or {})
    store = out / 'store'
    seconds = duration or NAVIGATION_SECONDS.get(world, 50.0) + 10.0
    # Each input is read by both nodes and by RORY's ring (both log: rory, replay). The ring
    # shares one reader between the nodes that read a topic (ring.py, SharedReader): with the
    # simulator up the graph shows three readers of /scan and of /odom (counted 2026-11-28).
    # The four once waited for were never there: the clock waited out the simulator's 30 s
    # --wait-timeout every run. (A node is RUNNING only once its ring readers matched.)
    run = SimRun(world, out / 'run', domain_id=domain_id, duration=seconds, driver='none',
                 wait_for={'/scan': 3, '/odom': 3},
                 sim_args=['--start-delay', '1.0'])
    run.add_node('supervisor', [sys.executable, '-m', 'rory_runtime.cli', 'supervise',
                                str(config)])
    spec = get_world(world)
    run.publish_once('/goal_pose', goal_message(world, spec.default_goal), subscribers=2)
    run.record('/navigator/status', String, qos=LATCHED)
    run.record('/e_stop', Bool, qos=LATCHED)
    striker = Striker(out / 'run' / 'sim.log', world, store, strikes)
    striker.start()
    wall_minus_mono = time.time() - time.monotonic()
    struck = [node for strike in strikes for node in strike.nodes]
    over_since: list[float] = []

    def over() -> bool:
        """Every strike struck, every struck node recovered, and the navigator's last word
        REACHED, all of it for ``settle`` s on end."""
        back = [e['node'] for e in store_events(store) if e['kind'] == 'recovered']
        statuses = run.recorded('/navigator/status')
        if (len(striker.done) < len(struck) or striker.errors
                or any(back.count(n) < struck.count(n) for n in set(struck))
                or not statuses or statuses[-1][1].data != 'REACHED'):
            over_since.clear()
            return False
        if not over_since:
            over_since.append(time.monotonic())
        return time.monotonic() >= over_since[0] + (settle or 0.0)

    try:
        result = run.run(stop_when=None if settle is None else over)
    finally:
        striker.stop()
    statuses: list[str] = []
    for msg in result.messages.get('/navigator/status', []):
        if not statuses or statuses[-1] != msg.data:
            statuses.append(msg.data)
    e_stop = [(t + wall_minus_mono, bool(m.data)) for m, t in
              zip(result.messages.get('/e_stop', []), result.received_at.get('/e_stop', []),
                  strict=True)]
    goal = spec.goals[spec.default_goal]
    distance = math.inf
    if result.ground_truth:
        _, x, y, _ = result.ground_truth[-1]
        distance = math.hypot(x - goal.x, y - goal.y)
    reached = bool(statuses) and statuses[-1] == 'REACHED' and distance <= GOAL_XY
    return StackResult(world, reached, distance, int(result.summary.get('collisions', 0)),
                       statuses, store_events(store), striker.done, e_stop, striker.errors)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the stack once and print what happened; exit 0 when the goal was reached."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.harness.stack', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--world', default='real_room')
    parser.add_argument('--strike', action='append', type=Strike.parse, default=[],
                        metavar='T:NODE[,NODE...]|T:all',
                        help='SIGKILL nodes T sim seconds in, all in one loop')
    parser.add_argument('--method', action='append', default=[], metavar='NODE=METHOD')
    parser.add_argument('--duration', type=float)
    parser.add_argument('--domain', type=int, default=98)
    parser.add_argument('--out', type=Path, default=Path('stack-out'))
    args = parser.parse_args(argv)
    methods = dict(m.split('=', 1) for m in args.method)
    result = run_stack(args.world, args.out, domain_id=args.domain, strikes=args.strike,
                       duration=args.duration, methods=methods)
    for node in NODES:
        for rec in result.recoveries(node):
            print(f'{node}: recovered in {rec["total_ms"]:.0f} ms')
    print(f'statuses {result.statuses}; goal {"reached" if result.reached else "NOT reached"} '
          f'({result.goal_distance:.2f} m), collisions {result.collisions}; e_stop '
          f'{[v for _, v in result.e_stop]}')
    for error in result.errors:
        print(f'error: {error}')
    return 0 if result.reached and not result.collisions and not result.errors else 1


if __name__ == '__main__':
    sys.exit(main())
