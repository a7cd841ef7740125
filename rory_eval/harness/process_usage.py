"""CPU and memory of a node's process tree, per process role, sampled while a run goes on.

The overhead of RORY is the supervisor, the warm standby and what recording and checkpoints
add inside the node. A single figure for the whole tree says how much, not where; and a run
of 30 s also carries one-time costs (the standby imports rclpy and starts its participant
while the node already runs) that a robot running for hours pays once. So the tree is read
about once a second and reported per role, for the whole run and for its second half (the
*steady* window, after every process is up), with each process's proportional set size (PSS:
a library shared by three processes is counted a third in each) beside the peak RSS (which
counts it whole in each).

Roles come from the command line: ``rory_runtime.cli supervise`` is the supervisor; its forks
name themselves (rory_runtime/supervisor/zygote.py): ``rory-zygote`` is the fork server,
``rory-standby`` a waiting standby, ``rory-spare`` a waiting spare fork (made without
rclpy.init), and a standby or spare that became a node, like a node forked cold,
shows the node's command: anything else is the node. CPU that the tree's reaped children used
(a crashed node) is reported as ``reaped``.
"""

from __future__ import annotations

import math
import os
import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rory_runtime.supervisor.zygote import SPARE_TITLE, STANDBY_TITLE, ZYGOTE_TITLE

ROLES = ('node', 'supervisor', 'zygote', 'standby', 'spare', 'reaped')
"""Every role a reading can be given, in report order."""

_CLK_TCK = float(os.sysconf('SC_CLK_TCK'))


def role_of(cmdline: Sequence[str]) -> str:
    """'supervisor', 'zygote', 'standby', 'spare' or 'node', from a process's command line (a
    fork of the zygote names itself: rory_runtime/supervisor/zygote.py)."""
    # A process whose title setproctitle touched shows its command line as one string.
    words = ' '.join(cmdline).split()
    first = words[0] if words else ''
    if first == ZYGOTE_TITLE:
        return 'zygote'
    if first == STANDBY_TITLE:
        return 'standby'
    if first == SPARE_TITLE:
        return 'spare'
    if 'rory_runtime.cli' in words and 'supervise' in words:
        return 'supervisor'
    return 'node'


@dataclass(frozen=True)
class ProcessReading:
    """One process at one moment."""

    pid: int
    role: str
    own_ticks: int  # utime + stime
    reaped_ticks: int  # cutime + cstime: its waited-for children
    peak_rss_mb: float  # VmHWM
    pss_mb: float  # NaN unless read (it costs a page-table walk)
    threads: tuple[tuple[str, int], ...] = ()  # ticks per thread kind (see thread_kind)


def read_process(pid: int, *, with_pss: bool = False,
                 proc: Path = Path('/proc')) -> ProcessReading | None:
    """pid's reading, or None if it is gone (or not readable)."""
    base = proc / str(pid)
    try:
        stat = (base / 'stat').read_text().rsplit(')', 1)[1].split()
        argv = (base / 'cmdline').read_bytes().split(b'\0')
        status = (base / 'status').read_text()
        pss = _pss_mb(base) if with_pss else math.nan
    except (OSError, IndexError):
        return None
    hwm = next((int(line.split()[1]) / 1024.0 for line in status.splitlines()
                if line.startswith('VmHWM:')), 0.0)
    return ProcessReading(
        pid, role_of([a.decode(errors='replace') for a in argv if a]),
        int(stat[11]) + int(stat[12]), int(stat[13]) + int(stat[14]), hwm, pss,
        _thread_ticks(base))


def thread_kind(comm: str) -> str:
    """A thread's name without its instance number or port: Fast DDS names its threads
    ``dds.udp.7411``, ``dds.ev.0``, ...; every Python thread is ``python``."""
    return re.sub(r'[.0-9]+$', '', comm) or comm


def _thread_ticks(base: Path) -> tuple[tuple[str, int], ...]:
    ticks: dict[str, int] = {}
    try:
        tasks = list((base / 'task').iterdir())
    except OSError:
        return ()
    for task in tasks:
        try:
            text = (task / 'stat').read_text()
        except OSError:
            continue  # the thread ended
        comm = text[text.index('(') + 1:text.rindex(')')]
        fields = text.rsplit(')', 1)[1].split()
        kind = thread_kind(comm)
        ticks[kind] = ticks.get(kind, 0) + int(fields[11]) + int(fields[12])
    return tuple(sorted(ticks.items()))


def _pss_mb(base: Path) -> float:
    for line in (base / 'smaps_rollup').read_text().splitlines():
        if line.startswith('Pss:'):
            return int(line.split()[1]) / 1024.0
    return math.nan


def tree_pids(root: int, *, proc: Path = Path('/proc')) -> list[int]:
    """root and every live descendant, by each process's parent."""
    children: dict[int, list[int]] = {}
    for entry in proc.iterdir():
        if entry.name.isdigit():
            try:
                ppid = int((entry / 'stat').read_text().rsplit(')', 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
            children.setdefault(ppid, []).append(int(entry.name))
    tree, todo = [], [root]
    while todo:
        pid = todo.pop()
        tree.append(pid)
        todo.extend(children.get(pid, ()))
    return tree


def tree_cpu_ticks(root: int, *, proc: Path = Path('/proc')) -> int:
    """CPU ticks of a process tree: each live member's own, plus what the members' reaped
    children used (a crashed node's time lands in its supervisor's cutime/cstime)."""
    total = 0
    for pid in tree_pids(root, proc=proc):
        reading = read_process(pid, proc=proc)
        if reading is not None:
            total += reading.own_ticks + reading.reaped_ticks
    return total


def peak_rss_mb(pid: int, *, proc: Path = Path('/proc')) -> float:
    """pid's peak RSS (VmHWM) in MB; 0 if it is gone."""
    reading = read_process(pid, proc=proc)
    return 0.0 if reading is None else reading.peak_rss_mb


@dataclass(frozen=True)
class RoleUsage:
    """What the processes of one role used."""

    processes: int
    cpu_seconds: float  # over the whole window
    steady_cpu_seconds: float  # over its second half
    peak_rss_mb: float  # sum of VmHWM: an upper bound, shared libraries counted per process
    pss_mb: float  # sum of PSS at the end: shared pages split between their users
    steady_threads: dict[str, float] = field(default_factory=dict)  # CPU s per thread kind


@dataclass(frozen=True)
class TreeUsage:
    """A process tree's use over a window, per role."""

    wall_seconds: float
    steady_wall_seconds: float
    roles: dict[str, RoleUsage]

    @property
    def cpu_seconds(self) -> float:
        """The whole tree over the whole window."""
        return sum(r.cpu_seconds for r in self.roles.values())

    @property
    def steady_cpu_percent(self) -> float:
        """The whole tree over the second half, in percent of one core."""
        steady = sum(r.steady_cpu_seconds for r in self.roles.values())
        return 100.0 * steady / max(self.steady_wall_seconds, 1e-9)

    @property
    def pss_mb(self) -> float:
        """The whole tree's PSS at the end."""
        return sum(r.pss_mb for r in self.roles.values())

    def to_json(self) -> dict[str, dict[str, Any]]:
        """Per role: processes, CPU% whole and steady, peak RSS and PSS (MB), and the steady
        CPU% of each kind of thread."""
        return {
            name: {'processes': r.processes,
                   'cpu_percent': round(100.0 * r.cpu_seconds / max(self.wall_seconds, 1e-9), 2),
                   'steady_cpu_percent': round(
                       100.0 * r.steady_cpu_seconds / max(self.steady_wall_seconds, 1e-9), 2),
                   'peak_rss_mb': round(r.peak_rss_mb, 1), 'pss_mb': round(r.pss_mb, 1),
                   'steady_threads_percent': {
                       kind: round(100.0 * seconds / max(self.steady_wall_seconds, 1e-9), 2)
                       for kind, seconds in r.steady_threads.items()}}
            for name, r in self.roles.items()}


@dataclass
class _Sample:
    at: float
    readings: dict[int, ProcessReading] = field(default_factory=dict)


class TreeSampler:
    """Reads a process tree at ``start()``, on each ``sample()`` and at ``finish()``.

    Args:
        root: the tree's root process (the node, or the supervisor).
        clock: monotonic seconds (a test passes its own).
        read: a process's reading (a test passes its own).
        pids: a tree's members (a test passes its own).
    """

    def __init__(self, root: int, *, clock: Callable[[], float] = time.monotonic,
                 read: Callable[..., ProcessReading | None] = read_process,
                 pids: Callable[[int], list[int]] = tree_pids) -> None:
        self.root = root
        self._clock = clock
        self._read = read
        self._pids = pids
        self._samples: list[_Sample] = []

    def _take(self, *, with_pss: bool = False) -> None:
        sample = _Sample(self._clock())
        for pid in self._pids(self.root):
            reading = self._read(pid, with_pss=with_pss)
            if reading is not None:
                sample.readings[pid] = reading
        self._samples.append(sample)

    def start(self) -> None:
        """The window opens now."""
        self._samples.clear()
        self._take()

    def sample(self) -> None:
        """A reading inside the window (about once a second is plenty)."""
        self._take()

    def finish(self) -> TreeUsage:
        """The window closes now; what each role used in it."""
        self._take(with_pss=True)
        first, last = self._samples[0], self._samples[-1]
        middle_at = first.at + (last.at - first.at) / 2.0
        middle = min(self._samples, key=lambda s: abs(s.at - middle_at))
        whole = _ticks_between(first, last)
        steady = _ticks_between(middle, last)
        roles: dict[str, RoleUsage] = {}
        for name in ROLES:
            members = [r for r in last.readings.values() if r.role == name]
            if name != 'reaped' and not members:
                continue
            if name == 'reaped' and not whole.get('reaped'):
                continue
            roles[name] = RoleUsage(
                len(members), whole.get(name, 0) / _CLK_TCK, steady.get(name, 0) / _CLK_TCK,
                sum(r.peak_rss_mb for r in members), sum(r.pss_mb for r in members),
                {kind: ticks / _CLK_TCK
                 for kind, ticks in _thread_ticks_between(middle, last, name).items()})
        return TreeUsage(last.at - first.at, last.at - middle.at, roles)


def _ticks_between(before: _Sample, after: _Sample) -> dict[str, int]:
    """Ticks per role from before to after. A process born in between counts from 0 (its
    whole life is inside); one that died is in its parent's reaped ticks."""
    ticks: dict[str, int] = {}
    for pid, now in after.readings.items():
        then = before.readings.get(pid)
        own = now.own_ticks - (then.own_ticks if then else 0)
        reaped = now.reaped_ticks - (then.reaped_ticks if then else 0)
        ticks[now.role] = ticks.get(now.role, 0) + own
        ticks['reaped'] = ticks.get('reaped', 0) + reaped
    return ticks


def _thread_ticks_between(before: _Sample, after: _Sample, role: str) -> dict[str, int]:
    """Ticks per thread kind of one role's processes from before to after, largest first.
    Threads that ended in between are not listed (their time is in the role's total)."""
    ticks: dict[str, int] = {}
    for pid, now in after.readings.items():
        if now.role != role:
            continue
        then = before.readings.get(pid)
        earlier = dict(then.threads) if then else {}
        for kind, n in now.threads:
            ticks[kind] = ticks.get(kind, 0) + max(0, n - earlier.get(kind, 0))
    return dict(sorted(ticks.items(), key=lambda kv: -kv[1]))
