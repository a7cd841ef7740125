"""Is a supervised node's process alive? Judged from its heartbeat and its checkpoints.

A node's runtime writes the steady clock into its in-flight slot every 0.2 s (``inflight.py``,
``InFlightSlot.beat``). :class:`Watchdog` reads it on each of the supervisor's ticks, on the
supervisor's clock (``ports.py``), and says what it finds: a process that never beats within
``start_timeout``, one that stops beating for ``hang_timeout``, one whose heartbeat is late
enough to be a hang in the making, one that beats but whose HELLO never reached the supervisor.
It decides: the findings are values ``ManagedNode`` gets back from :meth:`Watchdog.check`;
:func:`enforce` acts on those against the process (says them and signals it), and the node
keeps its inputs on a late :class:`Beat` (docs/architecture.md, "Heartbeat" and "At a crash:
S1-S4").
"""

from __future__ import annotations

import logging
import signal
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from ..inflight import InFlight
from .ports import EventSink
from .process import Child
from .states import LOG_PREFIX

_logger = logging.getLogger('rory.supervisor')

HELLO_TIMEOUT = 10.0
"""Seconds a new process may beat without its HELLO reaching the supervisor, by default (a
node's ``hello_timeout`` in the supervisor's config). Its runtime sends
HELLO right after its first callback, on the status socket (status_socket.py), so a beating
node whose HELLO never arrives is one that cannot reach its supervisor: only a new process
helps."""

HANG_DUMP_GRACE = 0.3
"""Seconds between SIGUSR1 (a hung node prints its threads' stacks) and SIGKILL."""

STALL_SUSPECT = 0.6
"""A heartbeat this late (3 beats; at most half of hang_timeout) may be a hang: the ring starts
taking the node's inputs (S2 early). A hang lasts hang_timeout before the kill, longer than
the ring's history covers on a busy topic (node depth + 16 messages: 2.3 s of 50 Hz odometry
for a depth of 100); from here on nothing is dropped however long the hang."""

OVERDUE_INTERVALS = 3
"""Checkpoint intervals a running node may go without a checkpoint before it is overdue
(WARN on /diagnostics and in the log): one late checkpoint is I/O, three are a cause."""


@dataclass(frozen=True)
class Beat:
    """The process beats; its last beat is ``age_s`` old. ``late``: old enough
    (:data:`STALL_SUSPECT`) that the node may be hanging, so its inputs are worth keeping."""

    age_s: float
    late: bool


@dataclass(frozen=True)
class Hung:
    """No first beat within ``start_timeout``, or no beat for ``hang_timeout``: send ``signal``.

    SIGUSR1 for a heartbeat that stopped (faulthandler prints the stacks; :class:`KillDue`
    follows after :data:`HANG_DUMP_GRACE`), SIGKILL for a process that never got going.
    """

    waiting_for: Literal['start', 'heartbeat']
    stalled_s: float
    limit_s: float
    signal: int


@dataclass(frozen=True)
class Unheard:
    """Beating for longer than its ``hello_timeout`` (:data:`HELLO_TIMEOUT` by default) without
    its HELLO heard: SIGKILL."""

    beating_s: float


@dataclass(frozen=True)
class KillDue:
    """The hung process has had its :data:`HANG_DUMP_GRACE` to print its stacks: SIGKILL."""


Finding = Beat | Hung | Unheard | KillDue


@dataclass(frozen=True)
class CheckpointsOverdue:
    """A running node's checkpoints are overdue; ``since_s``: since its last one, None if it
    never took one."""

    since_s: float | None


@dataclass
class _Watched:
    """What the watchdog knows of one process; a new one at each :meth:`Watchdog.watch`."""

    spawned_ns: int  # the clock's ns when it was started
    first_beat_ns: int | None = None  # the clock's ns when its first beat was seen
    kill_at: float | None = None  # SIGKILL due (SIGUSR1 sent: a stack dump)
    killed: bool = False  # SIGKILL decided: its exit is reaped as a crash
    kill_reason: str | None = None
    overdue_said: bool = False  # its checkpoints being overdue was said (once per lapse)


class Watchdog:
    """The liveness of one node's processes, one process at a time.

    Args:
        slot: The node's in-flight slot, where its heartbeat is.
        clock: Monotonic seconds (the supervisor's ports).
        read_beat: A slot's last beat on the clock's scale, in ns; None before the first.
        hang_timeout: Seconds without a beat before a process is hung (None: never).
        start_timeout: Seconds a new process may take to beat once (None: no limit).
        hello_timeout: Seconds a process may beat without its HELLO heard before it is killed.
    """

    def __init__(self, slot: Path, clock: Callable[[], float],
                 read_beat: Callable[[Path], int | None], hang_timeout: float | None,
                 start_timeout: float | None, hello_timeout: float = HELLO_TIMEOUT) -> None:
        self._slot = slot
        self._clock = clock
        self._read_beat = read_beat
        self._hang_timeout = hang_timeout
        self._start_timeout = start_timeout
        self._hello_timeout = hello_timeout
        self._late_after = (STALL_SUSPECT if hang_timeout is None
                            else min(STALL_SUSPECT, hang_timeout / 2))
        self._process = _Watched(0)
        self.last_checkpoint_at: float | None = None  # the clock's seconds, any process

    @property
    def slot(self) -> Path:
        """The node's in-flight slot, where its heartbeat is read."""
        return self._slot

    def _now_ns(self) -> int:
        return int(self._clock() * 1e9)

    def watch(self) -> None:
        """A new process starts now: judge it alone (an older beat is not its own)."""
        self._process = _Watched(self._now_ns())

    @property
    def kill_reason(self) -> str | None:
        """Why the watchdog judged the current process for killing (hung, unheard), if it did."""
        return self._process.kill_reason

    def check(self, now: float, heard: bool) -> list[Finding]:
        """Look at the current process's heartbeat, which it must have (it is live).

        Args:
            now: The clock's seconds at this tick.
            heard: Its HELLO reached the supervisor.

        Returns:
            In order: what its beat says (if it beats), then at most one signal to send.
            Once a SIGKILL is decided, nothing more: its exit is reaped as a crash.
        """
        process = self._process
        if process.killed:
            return []
        if process.kill_at is not None:
            if now >= process.kill_at:
                self._killed()
                return [KillDue()]
            return []
        now_ns = self._now_ns()
        beat = self._read_beat(self._slot)
        findings: list[Finding] = []
        limit: float | None
        if beat is None or beat < process.spawned_ns:
            # Not beating yet: still importing, initialising, constructing the node.
            limit, since, what = self._start_timeout, process.spawned_ns, 'start'
        else:
            limit, since, what = self._hang_timeout, beat, 'heartbeat'
            age_s = (now_ns - beat) / 1e9
            findings.append(Beat(age_s, age_s >= self._late_after))
            if process.first_beat_ns is None:
                process.first_beat_ns = now_ns
            beating_for = now_ns - process.first_beat_ns
            if not heard and beating_for > self._hello_timeout * 1e9:
                beating_s = beating_for / 1e9
                process.kill_reason = f'unheard (no HELLO after {beating_s:.1f} s of running)'
                self._killed()
                findings.append(Unheard(beating_s))
                return findings
        if limit is None or now_ns - since <= limit * 1e9:
            return findings
        stalled_s = (now_ns - since) / 1e9
        process.kill_reason = f'hung (no {what} for {stalled_s:.1f} s)'
        if what == 'heartbeat':
            process.kill_at = now + HANG_DUMP_GRACE
            findings.append(Hung('heartbeat', stalled_s, limit, signal.SIGUSR1))
        else:
            self._killed()
            findings.append(Hung('start', stalled_s, limit, signal.SIGKILL))
        return findings

    def _killed(self) -> None:
        self._process.killed = True
        self._process.kill_at = None

    def checkpoint_taken(self, now: float) -> None:
        """The node reported a checkpoint (at ``now``, the clock's seconds)."""
        self.last_checkpoint_at = now
        self._process.overdue_said = False

    def checkpoint_overdue(self, now: float, running_since: float | None,
                           interval: float) -> float | None:
        """Seconds past the time a running node must have checkpointed by, if it is late.

        Checkpoints come every interval of the node's ROS time: under ``use_sim_time`` with no
        /clock, or a /clock that stops, none come at all; so do failing ones.

        Args:
            running_since: When it was released, if it runs released (RUNNING) with a method
                that checkpoints; else None, and it is never overdue.
            interval: Its checkpoint interval in seconds.
        """
        if running_since is None:
            return None
        since = max(self.last_checkpoint_at or 0.0, running_since)
        late = now - since - OVERDUE_INTERVALS * interval
        return late if late > 0 else None

    def overdue_news(self, now: float, running_since: float | None,
                     interval: float) -> CheckpointsOverdue | None:
        """The checkpoints are overdue and nobody was told yet (once per process, and again
        only after a checkpoint came); arguments as :meth:`checkpoint_overdue`."""
        if (self._process.overdue_said
                or self.checkpoint_overdue(now, running_since, interval) is None):
            return None
        self._process.overdue_said = True
        last = self.last_checkpoint_at
        return CheckpointsOverdue(None if last is None else now - last)


# -- what the supervisor does and says of its findings --------------------------------------------


def enforce(finding: Hung | Unheard | KillDue, node_id: str, incarnation: int, child: Child,
            busy: Callable[[], InFlight | None], events: EventSink) -> None:
    """Act on a finding against the process ``child``, saying what it was doing (``busy``:
    the message it was applying, if any).

    SIGUSR1 for a heartbeat that stopped: faulthandler in the node prints every thread's stack,
    where it hung, and SIGKILL follows (:class:`KillDue`). SIGKILL at once for a process that
    never beat, and for one that runs but whose HELLO never arrived (replaced: a crash,
    recovered).
    """
    if isinstance(finding, Hung):
        say_hung(node_id, incarnation, child.pid, finding, busy(), events)
        child.send_signal(finding.signal)
    elif isinstance(finding, Unheard):
        say_unheard(node_id, incarnation, child.pid, finding, events)
        child.send_signal(signal.SIGKILL)
    else:  # KillDue: the hung process has printed its stacks
        child.send_signal(signal.SIGKILL)


def say_hung(node_id: str, incarnation: int, pid: int, hung: Hung, busy: InFlight | None,
             events: EventSink) -> None:
    """No first beat, or no beat for hang_timeout: what it was doing (``busy``: the message it
    was applying, if any), as an error and the ``hang`` event."""
    on = f' while applying {busy.topic} {busy.ident}' if busy is not None else ''
    _logger.error(
        '%s %s: hung: no %s for %.1f s (limit %.1f s)%s; killing pid %d', LOG_PREFIX,
        node_id, hung.waiting_for, hung.stalled_s, hung.limit_s, on, pid,
    )
    events.write(
        'hang', node_id, incarnation=incarnation,
        stalled_s=round(hung.stalled_s, 3),
        waiting_for=hung.waiting_for, topic=busy.topic if busy else None,
        source_ns=busy.ident[0] if busy else None, seq=busy.ident[1] if busy else None,
    )


def say_unheard(node_id: str, incarnation: int, pid: int, unheard: Unheard,
                events: EventSink) -> None:
    """The process runs but its HELLO never arrived: it is replaced (a crash, recovered)."""
    _logger.error(
        '%s %s: pid %d has run %.1f s without its HELLO reaching the supervisor (its '
        'status publisher was never discovered); replacing it', LOG_PREFIX, node_id,
        pid, unheard.beating_s,
    )
    events.write('unheard', node_id, incarnation=incarnation,
                 beating_s=round(unheard.beating_s, 3))


def say_overdue(node_id: str, overdue: CheckpointsOverdue, events: EventSink) -> None:
    """A running node's checkpoints are overdue: a warning and ``checkpoints_overdue``."""
    age_s = overdue.since_s
    _logger.warning(
        '%s %s: no checkpoint for %s: the interval follows the node\'s ROS time (under '
        'use_sim_time, is /clock advancing?), or its checkpoints fail (see its errors); '
        'a crash now loses more', LOG_PREFIX, node_id,
        'the whole run' if age_s is None else f'{age_s:.1f} s')
    events.write('checkpoints_overdue', node_id,
                 since_s=None if age_s is None else round(age_s, 1))
