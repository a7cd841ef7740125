"""``make faults``, storms in a row: the supervisor stays bounded through them (issue 38).

    python -m rory_eval.faults.storm_bound_campaign [--storms 20] [--nodes 3]

One bug often takes down every node that reads a message at once, and it can do so again and
again. One ``rory supervise`` runs N instrumented integrators (each its own node name and state
topic, all reading /numbers, method rory, the default standby pool: one per node, at most 3);
one publisher sends 1, 2, ... at 50 Hz for the whole campaign. Then come ``--storms`` storms in
a row, each:

1. once every node has run :data:`STABLE_RUN` s (the supervisor's ``stable_after`` and a
   half second: storms closer together are a crash loop to it, which it gives up after five),
   SIGKILL every node process in one loop (microseconds apart);
2. wait until every node is back (a ``recovered`` event, RUNNING again) and the pool is full
   again (each standby the pool holds has logged `` ready in ``), and at least
   :data:`SETTLE` s after the kill, so that the killed processes' DDS participants have
   outlived their lease (3 s) in the supervisor's discovery database;
3. read the supervisor: PSS and RSS (``/proc/PID/smaps_rollup``), open file descriptors
   (``/proc/PID/fd``), threads; its process tree by a PPID walk of /proc (nodes, standbys, the
   zygote, anything else, zombies); and the zygote's RSS and descriptors. Each figure is the
   least of :data:`SAMPLES` readings 0.1 s apart: what leaks stays, a thread or pipe in
   passing does not.

Bounded (:func:`judge`) when, after a warm-up of :data:`WARMUP` storms, no later storm's figure
is above the first one after the warm-up: descriptors, threads and processes exactly, memory
by at most :data:`MEMORY_TOLERANCE_MB` MB; and at every reading the tree is the N nodes, the
pool, the zygote and nothing else, no zombie. Then the publisher finishes, each node must have
applied every number exactly once, in order (its state topic's history), and the supervisor
is stopped as a user would (SIGINT): every process of its tree must be gone when it has exited.
With ``--out`` the run is kept, with the evidence behind each reading in ``readings.jsonl``
(descriptors by kind, the tree, the supervisor's memory by mapping and its unnamed mappings).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from rory_eval.harness.process_usage import role_of, tree_pids
from rory_eval.harness.scenario import (
    EXAMPLE,
    EventsFile,
    LineFollower,
    StateReader,
    child_process,
    integrators_config,
    joining,
    scenario_env,
)
from rory_eval.harness.simrun import exit_on_sigterm
from rory_runtime.supervisor.config import Backoff

RATE = 50.0
SECONDS_PER_STORM = 13.0  # what the publisher's count allows for each storm (~11.5 s used)
LEAD = 15.0  # and for the start, before the first storm
SETTLE = 4.0  # s after a strike before its reading: the killed participants' lease is 3 s
# Before each strike every node has run this long: the supervisor gives a node up after
# max_restarts (5) crashes in a row, a row being broken by a start that ran stable_after
# (10 s); 20 storms 4.5 s apart are a crash loop to it (storm 6 of a first try: FATAL).
STABLE_RUN = Backoff().stable_after + 0.5
SAMPLES = 5
SAMPLE_GAP = 0.1
WARMUP = 2
MEMORY_TOLERANCE_MB = 2.0
STORM_TIMEOUT = 60.0
MAX_POOL = 3  # the default pool: one standby per node, at most this many

_READY = re.compile(r'standby pid (\d+) ready in ')
_ENDED = re.compile(r'standby pid (\d+) (?:had ended|ended before it was ready)')


@dataclasses.dataclass(frozen=True)
class Member:
    """One process of the supervisor's tree (not the supervisor)."""

    pid: int
    ppid: int
    role: str  # node, standby, zygote (process_usage.role_of), zombie, or other
    cmdline: str


@dataclasses.dataclass(frozen=True)
class Reading:
    """The supervisor and its tree after one storm (storm 0: before the first)."""

    storm: int
    pss_mb: float
    rss_mb: float
    fds: int
    threads: int
    nodes: int
    standbys: int  # waiting standbys and spare forks
    zygotes: int
    others: int  # live processes of the tree that are neither a node, a standby nor the zygote
    zombies: int
    zygote_rss_mb: float
    zygote_fds: int
    recovered_ms: float = 0.0  # the storm's slowest recovery (crash detected -> released)
    warm: int = 0  # nodes that came back from a standby
    publishing: bool = True  # the publisher was still sending when the storm struck
    fd_kinds: dict[str, int] = dataclasses.field(default_factory=dict, compare=False)
    members: tuple[Member, ...] = dataclasses.field(default=(), compare=False)

    @property
    def processes(self) -> int:
        """Live processes of the tree below the supervisor."""
        return self.nodes + self.standbys + self.zygotes + self.others


@dataclasses.dataclass
class Verdict:
    """What :func:`judge` found."""

    failures: list[str]
    notes: list[str]

    @property
    def bounded(self) -> bool:
        return not self.failures


# -- reading /proc ----------------------------------------------------------------------------

def _kb_fields(path: Path, names: Sequence[str]) -> dict[str, float]:
    """``Name:  123 kB`` lines of a /proc file, in MB."""
    found: dict[str, float] = {}
    for line in path.read_text().splitlines():
        key, _, rest = line.partition(':')
        if key in names:
            found[key] = int(rest.split()[0]) / 1024.0
    return found


def fd_kind(target: str) -> str:
    """What a descriptor is, without its inode: ``pipe``, ``socket``,
    ``anon_inode:[eventpoll]``, or the file's path."""
    match = re.fullmatch(r'(pipe|socket):\[\d+\]', target)
    return match.group(1) if match else target


def fd_kinds(pid: int, proc: Path = Path('/proc')) -> dict[str, int]:
    """pid's open descriptors, counted by :func:`fd_kind`."""
    kinds: Counter[str] = Counter()
    for entry in (proc / str(pid) / 'fd').iterdir():
        try:
            kinds[fd_kind(os.readlink(entry))] += 1
        except OSError:
            continue  # closed meanwhile
    return dict(kinds)


def members(root: int, node_pids: set[int] | None = None,
            proc: Path = Path('/proc')) -> tuple[Member, ...]:
    """Every process below root (by PPID) and its role: ``zombie``, ``zygote`` or
    ``standby`` (their titles), ``node`` (one of ``node_pids``; any not a zygote or standby
    when None), else ``other``."""
    found = []
    for pid in tree_pids(root, proc=proc):
        if pid == root:
            continue
        base = proc / str(pid)
        try:
            stat = (base / 'stat').read_text().rsplit(')', 1)[1].split()
            argv = [a.decode(errors='replace') for a in (base / 'cmdline').read_bytes().split(b'\0')
                    if a]
        except (OSError, IndexError):
            continue  # gone meanwhile
        role = 'zombie' if stat[0] in ('Z', 'X') else role_of(argv)
        if role == 'node' and node_pids is not None and pid not in node_pids:
            role = 'other'
        found.append(Member(pid, int(stat[1]), role, ' '.join(argv)))
    return tuple(found)


def read_once(sup: int, storm: int, node_pids: set[int] | None = None,
              proc: Path = Path('/proc')) -> Reading:
    """One reading of the supervisor ``sup`` and its tree (``node_pids``: the node processes
    it runs, as its events name them)."""
    base = proc / str(sup)
    memory = _kb_fields(base / 'smaps_rollup', ('Pss', 'Rss'))
    threads = int(next(line.split()[1] for line in (base / 'status').read_text().splitlines()
                       if line.startswith('Threads:')))
    kinds = fd_kinds(sup, proc)
    tree = members(sup, node_pids, proc)
    roles = Counter(m.role for m in tree)
    zygotes = [m.pid for m in tree if m.role == 'zygote']
    zygote_rss, zygote_fds = 0.0, 0
    if len(zygotes) == 1:
        zygote_rss = _kb_fields(proc / str(zygotes[0]) / 'status', ('VmRSS',)).get('VmRSS', 0.0)
        zygote_fds = sum(fd_kinds(zygotes[0], proc).values())
    return Reading(storm, memory['Pss'], memory['Rss'], sum(kinds.values()), threads,
                   roles['node'], roles['standby'] + roles['spare'], roles['zygote'],
                   roles['other'],
                   roles['zombie'],
                   zygote_rss, zygote_fds, fd_kinds=kinds, members=tree)


def memory_by_mapping(pid: int, proc: Path = Path('/proc')) -> dict[str, dict[str, float]]:
    """pid's memory by what is mapped (``[heap]``, ``[anon]`` for unnamed mappings,
    ``[stack]``, or the file's path): mappings, RSS and PSS (MB) and private dirty (MB) of
    each; what a growth of the totals is made of."""
    found: dict[str, dict[str, float]] = {}
    current: dict[str, float] | None = None
    for line in (proc / str(pid) / 'smaps').read_text().splitlines():
        head = line.split(None, 5)
        if len(head) >= 5 and '-' in head[0] and not head[0].endswith(':'):
            name = head[5].strip() if len(head) > 5 else '[anon]'
            current = found.setdefault(name, {'maps': 0, 'rss': 0.0, 'pss': 0.0,
                                              'private_dirty': 0.0})
            current['maps'] += 1
        elif current is not None and head and head[0] in ('Rss:', 'Pss:', 'Private_Dirty:'):
            key = head[0][:-1].lower()
            current[key] += int(head[1]) / 1024.0
    return found


def anonymous_mappings(pid: int, proc: Path = Path('/proc'),
                       at_least_mb: float = 0.1) -> dict[str, dict[str, float]]:
    """pid's unnamed mappings (malloc arenas, Python's, thread stacks) of at least
    ``at_least_mb`` resident, by address range: size, RSS and private dirty (MB)."""
    found: dict[str, dict[str, float]] = {}
    current: dict[str, float] | None = None
    for line in (proc / str(pid) / 'smaps').read_text().splitlines():
        head = line.split()
        if len(head) >= 5 and '-' in head[0] and not head[0].endswith(':'):
            current = {'size': 0.0, 'rss': 0.0, 'private_dirty': 0.0} if len(head) == 5 else None
            if current is not None:
                found[head[0]] = current
        elif current is not None and head and head[0] in ('Size:', 'Rss:', 'Private_Dirty:'):
            current[head[0][:-1].lower()] = int(head[1]) / 1024.0
    return {k: v for k, v in found.items() if v['rss'] >= at_least_mb}


def least(readings: Sequence[Reading]) -> Reading:
    """Each figure's least value over ``readings`` of one moment (what lasts); the
    descriptors by kind of the reading with the fewest, the tree of the smallest."""
    fewest = min(readings, key=lambda r: r.fds)
    return dataclasses.replace(
        fewest, pss_mb=min(r.pss_mb for r in readings), rss_mb=min(r.rss_mb for r in readings),
        threads=min(r.threads for r in readings), nodes=min(r.nodes for r in readings),
        standbys=min(r.standbys for r in readings), zygotes=min(r.zygotes for r in readings),
        others=min(r.others for r in readings), zombies=min(r.zombies for r in readings),
        zygote_rss_mb=min(r.zygote_rss_mb for r in readings),
        zygote_fds=min(r.zygote_fds for r in readings),
        members=min((r.members for r in readings), key=len))


def read_settled(sup: int, storm: int, node_pids: set[int] | None = None,
                 sleep: Callable[[float], None] = time.sleep,
                 proc: Path = Path('/proc')) -> Reading:
    """:func:`least` of :data:`SAMPLES` readings :data:`SAMPLE_GAP` s apart."""
    readings = []
    for i in range(SAMPLES):
        if i:
            sleep(SAMPLE_GAP)
        readings.append(read_once(sup, storm, node_pids, proc))
    return least(readings)


# -- the verdict ------------------------------------------------------------------------------

def judge(readings: Sequence[Reading], *, nodes: int, pool: int, warmup: int = WARMUP,
          tolerance_mb: float = MEMORY_TOLERANCE_MB) -> Verdict:
    """Bounded: after ``warmup`` storms no storm's figure above the first one's after the
    warm-up (descriptors, threads, processes exactly; memory by at most ``tolerance_mb``), and
    at every reading the tree is ``nodes`` nodes, ``pool`` standbys and one zygote, no
    zombie, nothing else."""
    failures: list[str] = []
    notes: list[str] = []
    for r in readings:
        tree = (r.nodes, r.standbys, r.zygotes, r.others)
        if tree != (nodes, pool, 1, 0):
            failures.append(f'storm {r.storm}: {r.nodes} nodes, {r.standbys} standbys, '
                            f'{r.zygotes} zygotes, {r.others} others (expected {nodes} nodes, '
                            f'{pool} standbys, 1 zygote, nothing else)')
        if r.zombies:
            failures.append(f'storm {r.storm}: {r.zombies} zombies in the tree')
    storms = [r for r in readings if r.storm >= 1]
    if len(storms) <= warmup:
        failures.append(f'{len(storms)} storms: none after the warm-up of {warmup}')
        return Verdict(failures, notes)
    base, rest = storms[warmup], storms[warmup:]
    exact: list[tuple[str, Callable[[Reading], float]]] = [
        ('descriptors', lambda r: r.fds), ('threads', lambda r: r.threads),
        ('processes', lambda r: r.processes), ('zygote descriptors', lambda r: r.zygote_fds)]
    memory: list[tuple[str, Callable[[Reading], float]]] = [
        ('PSS', lambda r: r.pss_mb), ('RSS', lambda r: r.rss_mb),
        ('zygote RSS', lambda r: r.zygote_rss_mb)]
    for name, get in exact:
        grew = [r for r in rest if get(r) > get(base)]
        if grew:
            failures.append(f'{name} grew: {get(base):g} at storm {base.storm}, '
                            + ', '.join(f'{get(r):g} at storm {r.storm}' for r in grew))
        elif any(get(r) != get(base) for r in rest):
            notes.append(f'{name} fell below storm {base.storm}\'s {get(base):g} '
                         f'(least {min(get(r) for r in rest):g})')
    for name, get in memory:
        top = max(rest, key=get)
        change = get(top) - get(base)
        if change > tolerance_mb:
            failures.append(f'{name} grew {change:+.1f} MB: {get(base):.1f} MB at storm '
                            f'{base.storm}, {get(top):.1f} at storm {top.storm} (tolerance '
                            f'+{tolerance_mb:g} MB)')
        last = rest[-1]
        notes.append(f'{name}: {get(base):.1f} MB at storm {base.storm}, {get(last):.1f} at '
                     f'storm {last.storm} ({get(last) - get(base):+.1f}), highest '
                     f'{get(top):.1f} at storm {top.storm}')
    if failures and rest[-1].fds != base.fds:
        kinds = kinds_change(base.fd_kinds, rest[-1].fd_kinds)
        notes.append(f'descriptors, storm {base.storm} -> {rest[-1].storm}: {kinds}')
    return Verdict(failures, notes)


def kinds_change(before: dict[str, int], after: dict[str, int]) -> str:
    """What differs between two descriptor counts by kind, e.g. ``pipe +6, socket -1``."""
    changes = [(k, after.get(k, 0) - before.get(k, 0)) for k in sorted({*before, *after})]
    return ', '.join(f'{k} {d:+d}' for k, d in changes if d) or 'none'


def table(readings: Sequence[Reading]) -> str:
    """One Markdown row per reading."""
    lines = [
        '| storm | slowest recovery (ms) | warm | PSS (MB) | RSS (MB) | fds | threads | '
        'processes (nodes + standbys + zygote + other) | zombies | zygote RSS (MB) | '
        'zygote fds |',
        '|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|---:|',
    ]
    for r in readings:
        storm = 'before' if r.storm == 0 else f'{r.storm}{"" if r.publishing else " (idle)"}'
        recovered = '-' if r.storm == 0 else f'{r.recovered_ms:.0f}'
        warm = '-' if r.storm == 0 else f'{r.warm}/{r.nodes}'
        lines.append(
            f'| {storm} | {recovered} | {warm} | {r.pss_mb:.1f} | {r.rss_mb:.1f} | {r.fds} | '
            f'{r.threads} | {r.processes} ({r.nodes} + {r.standbys} + {r.zygotes} + '
            f'{r.others}) | {r.zombies} | {r.zygote_rss_mb:.1f} | {r.zygote_fds} |')
    return '\n'.join(lines)


# -- the run ----------------------------------------------------------------------------------

def _stat(pid: int, proc: Path = Path('/proc')) -> tuple[str, int] | None:
    """A process's state letter and start time in ticks (which tells it from a later process
    with its pid), None if it is gone."""
    try:
        fields = (proc / str(pid) / 'stat').read_text().rsplit(')', 1)[1].split()
        return fields[0], int(fields[19])
    except (OSError, IndexError, ValueError):
        return None


def still_there(started: dict[int, int], proc: Path = Path('/proc')) -> dict[int, str]:
    """The processes of ``started`` (pid -> start time) that still exist: pid -> state letter
    (``Z``: a zombie, dead but not yet waited for)."""
    found = {}
    for pid, at in started.items():
        now = _stat(pid, proc)
        if now is not None and now[1] == at:
            found[pid] = now[0]
    return found


class _LogFollower:
    """Whole lines appended to the supervisor's log since the last poll."""

    def __init__(self, path: Path) -> None:
        self._lines = LineFollower(path)

    def poll(self) -> list[str]:
        return [line.decode(errors='replace') for line in self._lines.poll()]


@dataclasses.dataclass
class Campaign:
    """What one campaign produced."""

    nodes: int
    pool: int
    count: int = 0  # numbers published
    readings: list[Reading] = dataclasses.field(default_factory=list)
    exact: dict[str, bool] = dataclasses.field(default_factory=dict)
    stop_code: int | None = None
    tree_at_stop: list[Member] = dataclasses.field(default_factory=list)
    # Of tree_at_stop, pid -> state letter: when the supervisor had exited, and 2 s later.
    left_at_exit: dict[int, str] = dataclasses.field(default_factory=dict)
    left_later: dict[int, str] = dataclasses.field(default_factory=dict)
    error: str = ''

    def end_failures(self) -> list[str]:
        """What went wrong apart from the bounds."""
        found = [self.error] if self.error else []
        found += [f'{name} did not apply 1..{self.count} exactly once, in order'
                  for name, ok in self.exact.items() if not ok]
        if not self.error and len(self.exact) != self.nodes:
            found.append('exactness not checked')
        alive = {pid: st for pid, st in self.left_at_exit.items() if st not in 'ZX'}
        if alive:
            found.append(f'processes alive when the supervisor had exited: {alive}')
        if self.left_later:
            found.append(f'processes left 2 s after the supervisor exited: {self.left_later}')
        return found


def run_campaign(workdir: Path, domain_id: int, *, storms: int, nodes: int,
                 rate: float = RATE, log: Callable[[str], None] = print) -> Campaign:
    """The campaign in ``workdir``, ROS domain ``domain_id``; reaps every process it
    started."""
    workdir = workdir.resolve()
    names = [f'n{i}' for i in range(nodes)]
    pool = max(1, min(MAX_POOL, nodes))
    result = Campaign(nodes, pool)
    result.count = count = int(rate * (storms * SECONDS_PER_STORM + LEAD))
    config = integrators_config(workdir, names)
    env = scenario_env(domain_id)
    with joining(domain_id):
        reader = StateReader(domain_id, names, 'storm_bound_reader')
    events = EventsFile(workdir / 'store-rory' / 'events.jsonl')
    sup_log = workdir / 'supervisor.log'
    lines = _LogFollower(sup_log)
    pids: dict[str, int] = {}
    state: dict[str, str] = {}
    running_since: dict[str, float] = {}  # when this process saw each node become RUNNING
    standbys: set[int] = set()
    activated: set[int] = set()
    ready: set[int] = set()
    ended: set[int] = set()

    def poll() -> None:
        for ev in events.poll():
            if ev['kind'] == 'spawn':
                pids[ev['node']] = ev['pid']
                if ev.get('warm'):
                    activated.add(ev['pid'])
            elif ev['kind'] == 'state':
                state[ev['node']] = ev['new']
                if ev['new'] == 'RUNNING':
                    running_since[ev['node']] = time.monotonic()
            elif ev['kind'] == 'standby':
                standbys.add(ev['pid'])
        for line in lines.poll():
            if m := _READY.search(line):
                ready.add(int(m.group(1)))
            elif m := _ENDED.search(line):
                ended.add(int(m.group(1)))

    def pool_full() -> bool:
        waiting = standbys - activated - ended
        return len(waiting) == pool and waiting <= ready

    def wait_until(what: str, done: Callable[[], bool], timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while True:
            poll()
            if done():
                return
            if sup.poll() is not None:
                raise RuntimeError(f'the supervisor exited ({what}):\n'
                                   f'{sup_log.read_text()[-3000:]}')
            if time.monotonic() > deadline:
                raise RuntimeError(f'{what} within {timeout:g} s:\n{sup_log.read_text()[-3000:]}')
            time.sleep(0.01)

    try:
        with child_process([sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config)],
                           env, workdir, sup_log) as sup:
            wait_until('the nodes never ran',
                       lambda: all(state.get(n) == 'RUNNING' for n in names), 60.0)
            publisher = [sys.executable, str(EXAMPLE / 'count_publisher.py'), str(count),
                         str(rate), str(nodes + 1)]  # the nodes and the ring's one reader
            with child_process(publisher, env, workdir, workdir / 'publisher.log') as pub:
                wait_until('no number was applied', lambda: all(
                    reader.state[n].get('count', 0) > 0 for n in names), 30.0)
                wait_until('the pool never filled', pool_full, 30.0)
                result.readings.append(read_settled(sup.pid, 0, set(pids.values())))
                _keep(workdir, sup.pid, result.readings[-1])
                log(f'before: {_row(result.readings[-1])}')
                for storm in range(1, storms + 1):
                    wait_until('a node did not run stably', lambda: all(
                        state.get(n) == 'RUNNING'
                        and time.monotonic() - running_since[n] >= STABLE_RUN for n in names),
                        STABLE_RUN + STORM_TIMEOUT)
                    result.readings.append(
                        _storm(storm, names, pids, events, sup.pid, pub.poll() is None,
                               lambda what, done: wait_until(what, done, STORM_TIMEOUT),
                               pool_full, state))
                    _keep(workdir, sup.pid, result.readings[-1])
                    log(f'storm {storm}: {_row(result.readings[-1])}')
                wait_until('the publisher never finished', lambda: pub.poll() is not None,
                           count / rate + 60.0)
                if pub.returncode != 0:
                    raise RuntimeError(f'the publisher failed ({pub.returncode}):\n'
                                       f'{(workdir / "publisher.log").read_text()[-2000:]}')
            wait_until('the nodes never all applied the last number', lambda: all(
                reader.state[n].get('count') == count for n in names), 60.0)
            result.exact = {n: reader.state[n].get('history') == list(range(1, count + 1))
                            for n in names}
            # Stopped as a user would: Ctrl-C (SIGINT); every process of its tree must go.
            result.tree_at_stop = list(members(sup.pid))
            started = {m.pid: st[1] for m in result.tree_at_stop
                       if (st := _stat(m.pid)) is not None}
            sup.send_signal(signal.SIGINT)
            try:
                result.stop_code = sup.wait(timeout=30)
            except subprocess.TimeoutExpired:
                raise RuntimeError('the supervisor did not exit within 30 s of SIGINT') from None
            result.left_at_exit = still_there(started)
            time.sleep(2.0)
            result.left_later = still_there(started)
    except RuntimeError as err:
        result.error = str(err).splitlines()[0]
        log(str(err))
    finally:
        reader.close()
    return result


def _storm(storm: int, names: list[str], pids: dict[str, int], events: EventsFile, sup: int,
           publishing: bool, wait_until: Callable[[str, Callable[[], bool]], None],
           pool_full: Callable[[], bool], state: dict[str, str]) -> Reading:
    """Strike every node at once, wait until all are back and the pool full, read."""
    mark = len(events.events)
    struck = time.monotonic()
    for name in names:
        # One that died on its own a moment ago has its recovery awaited all the same.
        with contextlib.suppress(ProcessLookupError):
            os.kill(pids[name], signal.SIGKILL)

    def since() -> list[dict[str, Any]]:
        return events.events[mark:]

    wait_until(f'storm {storm}: not every node recovered', lambda: {
        e['node'] for e in since() if e['kind'] == 'recovered'} >= set(names)
        and all(state.get(n) == 'RUNNING' for n in names))
    wait_until(f'storm {storm}: the pool never filled again', pool_full)
    wait_until(f'storm {storm}: settling', lambda: time.monotonic() - struck >= SETTLE)
    reading = read_settled(sup, storm, set(pids.values()))
    recovered = [float(e['total_ms']) for e in since() if e['kind'] == 'recovered']
    warm = sum(1 for e in since() if e['kind'] == 'spawn' and e.get('warm'))
    return dataclasses.replace(reading, recovered_ms=max(recovered, default=0.0), warm=warm,
                               publishing=publishing)


def _keep(workdir: Path, sup: int, reading: Reading) -> None:
    """The evidence behind a reading, in ``workdir/readings.jsonl``: its descriptors by kind,
    its tree, and the supervisor's memory by mapping."""
    record = {'storm': reading.storm, 'fd_kinds': reading.fd_kinds,
              'members': [dataclasses.asdict(m) for m in reading.members],
              'memory_by_mapping': memory_by_mapping(sup),
              'anonymous': anonymous_mappings(sup)}
    with (workdir / 'readings.jsonl').open('a') as out:
        out.write(json.dumps(record) + '\n')


def _row(r: Reading) -> str:
    return (f'PSS {r.pss_mb:.1f} MB, RSS {r.rss_mb:.1f} MB, {r.fds} fds, {r.threads} threads, '
            f'{r.processes} processes ({r.nodes} nodes, {r.standbys} standbys, {r.zygotes} '
            f'zygote, {r.others} other), {r.zombies} zombies; zygote RSS {r.zygote_rss_mb:.1f} '
            f'MB, {r.zygote_fds} fds'
            + ('' if r.storm == 0 else f'; slowest recovery {r.recovered_ms:.0f} ms, '
               f'{r.warm} warm'))


def report(result: Campaign, verdict: Verdict) -> str:
    """The table, the verdict and the end's checks, as Markdown."""
    out = [table(result.readings), '']
    bounded = verdict.bounded and not result.error
    out.append(f'**{"BOUNDED" if bounded else "NOT BOUNDED"}** through '
               f'{sum(r.storm >= 1 for r in result.readings)} storms of {result.nodes} nodes '
               f'(pool of {result.pool}; warm-up {WARMUP} storms; descriptors, threads and '
               f'processes exactly constant after it, memory within +{MEMORY_TOLERANCE_MB:g} MB '
               f'of storm {WARMUP + 1}\'s)')
    out += [f'- {line}' for line in verdict.failures + verdict.notes]
    if result.exact:
        out.append(f'- exact: {sum(result.exact.values())} of {result.nodes} nodes applied '
                   f'1..{result.count} exactly once, in order')
    if result.tree_at_stop:
        out.append(f'- stopped with SIGINT: exit code {result.stop_code}; '
                   f'{len(result.tree_at_stop)} processes in its tree then, '
                   f'{len(result.left_at_exit)} left when it had exited '
                   f'({sum(st in "ZX" for st in result.left_at_exit.values())} of them '
                   'zombies), '
                   f'{len(result.left_later)} 2 s later')
    out += [f'- FAILED: {line}' for line in result.end_failures()]
    return '\n'.join(out)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the campaign; exit 1 unless bounded, exact and stopped clean."""
    exit_on_sigterm()
    parser = argparse.ArgumentParser(prog='python -m rory_eval.faults.storm_bound_campaign',
                                     description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--storms', type=int, default=20, help='storms in a row')
    parser.add_argument('--nodes', type=int, default=3, help='nodes, all struck in each storm')
    parser.add_argument('--domain', type=int, default=94, help='ROS domain id to use')
    parser.add_argument('--out', help='keep the run here (default: a temporary folder)')
    args = parser.parse_args(argv)
    if args.storms <= WARMUP:
        parser.error(f'--storms must be more than the warm-up of {WARMUP}')
    if args.nodes < 1:
        parser.error('--nodes must be at least 1')
    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix='rory-storm-bound-'))
    began = time.monotonic()
    result = run_campaign(root, args.domain, storms=args.storms, nodes=args.nodes)
    verdict = judge(result.readings, nodes=result.nodes, pool=result.pool)
    ok = verdict.bounded and not result.end_failures()
    text = report(result, verdict)
    print(f'\n{text}\n\n{(time.monotonic() - began) / 60:.1f} min'
          f'{"" if ok or args.out else f"; kept in {root}"}', flush=True)
    (root / 'storm_bound.md').write_text(text + '\n')
    if ok and not args.out:
        shutil.rmtree(root, ignore_errors=True)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
