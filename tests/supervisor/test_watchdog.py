"""The watchdog's judgements (rory_runtime/supervisor/watchdog.py) on a fake clock and a fake
heartbeat: start timeout, hang and its stack dump, a late beat, a process never heard, and
checkpoints overdue. No process, no ROS."""

from __future__ import annotations

import signal
import time
from pathlib import Path
from typing import cast

import pytest
from fake_supervisor import FakeChild, FakeClock, FakeEvents

from rory_runtime.inflight import InFlight
from rory_runtime.supervisor.process import reap
from rory_runtime.supervisor.watchdog import (
    HANG_DUMP_GRACE,
    HELLO_TIMEOUT,
    OVERDUE_INTERVALS,
    STALL_SUSPECT,
    Beat,
    CheckpointsOverdue,
    Hung,
    KillDue,
    Unheard,
    Watchdog,
    enforce,
)

SLOT = Path('/nonexistent/slot')


class Beats:
    """A clock that moves when told, and the node's heartbeat on it."""

    def __init__(self) -> None:
        self.now = 1000.0
        self.last: int | None = None

    def clock(self) -> float:
        return self.now

    def read(self, slot: Path) -> int | None:
        assert slot == SLOT
        return self.last

    def beat(self) -> None:
        self.last = int(self.now * 1e9)

    def advance(self, seconds: float) -> float:
        self.now += seconds
        return self.now



def near(value: float) -> float:
    """``pytest.approx(value)`` where a float is expected: it compares equal to one."""
    return cast(float, pytest.approx(value))

def _watchdog(hang: float | None = 5.0, start: float | None = 30.0) -> tuple[Watchdog, Beats]:
    beats = Beats()
    dog = Watchdog(SLOT, beats.clock, beats.read, hang_timeout=hang, start_timeout=start)
    dog.watch()
    return dog, beats


def test_a_process_that_never_beats_is_killed_at_its_start_timeout_and_only_once() -> None:
    dog, beats = _watchdog(start=30.0)
    assert dog.check(beats.advance(29.0), heard=False) == []
    (hung,) = dog.check(beats.advance(2.0), heard=False)
    assert hung == Hung('start', near(31.0), 30.0, signal.SIGKILL)
    assert dog.kill_reason == 'hung (no start for 31.0 s)'
    assert dog.check(beats.advance(5.0), heard=False) == []  # its exit is reaped as a crash


def test_no_start_timeout_waits_for_the_first_beat_for_ever() -> None:
    dog, beats = _watchdog(start=None)
    assert dog.check(beats.advance(3600.0), heard=False) == []


def test_a_beat_from_before_the_process_started_is_not_its_own() -> None:
    dog, beats = _watchdog(start=30.0)
    beats.beat()  # the previous process's last beat
    beats.advance(1.0)
    dog.watch()
    assert dog.check(beats.advance(31.0), heard=True)[0] == Hung(
        'start', near(31.0), 30.0, signal.SIGKILL)


def test_a_beating_process_is_reported_on_time_however_long_it_runs() -> None:
    dog, beats = _watchdog(hang=5.0)
    for _ in range(20):
        beats.advance(1.0)
        beats.beat()
        assert dog.check(beats.advance(0.2), heard=True) == [Beat(near(0.2), False)]
    assert dog.kill_reason is None


def test_a_beat_older_than_stall_suspect_is_late_at_most_half_the_hang_timeout() -> None:
    dog, beats = _watchdog(hang=5.0)
    beats.beat()
    (beat,) = dog.check(beats.advance(STALL_SUSPECT - 0.1), heard=True)
    assert isinstance(beat, Beat) and not beat.late
    (beat,) = dog.check(beats.advance(0.1), heard=True)
    assert beat == Beat(near(STALL_SUSPECT), True)
    short, beats = _watchdog(hang=0.8)
    beats.beat()
    (beat,) = short.check(beats.advance(0.4), heard=True)
    assert isinstance(beat, Beat) and beat.late


def test_a_hung_process_gets_sigusr1_then_sigkill_after_the_dump_grace() -> None:
    dog, beats = _watchdog(hang=5.0)
    beats.beat()
    assert dog.check(beats.advance(5.0), heard=True) == [Beat(5.0, True)]
    late, hung = dog.check(beats.advance(0.5), heard=True)
    assert late == Beat(near(5.5), True)
    assert hung == Hung('heartbeat', near(5.5), 5.0, signal.SIGUSR1)
    assert dog.kill_reason == 'hung (no heartbeat for 5.5 s)'
    assert dog.check(beats.advance(HANG_DUMP_GRACE / 2), heard=True) == []  # dumping
    assert dog.check(beats.advance(HANG_DUMP_GRACE / 2), heard=True) == [KillDue()]
    assert dog.check(beats.advance(1.0), heard=True) == []


def test_without_a_hang_timeout_a_silent_process_is_only_late() -> None:
    dog, beats = _watchdog(hang=None)
    beats.beat()
    assert dog.check(beats.advance(600.0), heard=True) == [Beat(600.0, True)]


def test_a_process_beating_but_never_heard_is_killed_once() -> None:
    dog, beats = _watchdog()
    findings: list[object] = []
    for _ in range(int(HELLO_TIMEOUT) + 2):
        beats.beat()
        findings += dog.check(beats.advance(1.0), heard=False)
    unheard = [f for f in findings if isinstance(f, Unheard)]
    assert len(unheard) == 1 and unheard[0].beating_s > HELLO_TIMEOUT
    assert dog.kill_reason is not None and dog.kill_reason.startswith('unheard (no HELLO after')


def test_a_process_never_heard_is_killed_at_its_own_hello_timeout() -> None:
    beats = Beats()
    dog = Watchdog(SLOT, beats.clock, beats.read, hang_timeout=5.0, start_timeout=30.0,
                   hello_timeout=1.5)
    dog.watch()
    beats.beat()
    assert [type(f) for f in dog.check(beats.advance(0.1), heard=False)] == [Beat]
    beats.beat()
    assert [type(f) for f in dog.check(beats.advance(1.4), heard=False)] == [Beat]
    beats.beat()
    findings = dog.check(beats.advance(0.2), heard=False)
    unheard = [f for f in findings if isinstance(f, Unheard)]
    assert len(unheard) == 1 and unheard[0].beating_s == near(1.6)


def test_a_heard_process_is_never_unheard() -> None:
    dog, beats = _watchdog()
    for _ in range(int(HELLO_TIMEOUT) * 3):
        beats.beat()
        assert all(isinstance(f, Beat) for f in dog.check(beats.advance(1.0), heard=True))


def test_a_new_process_starts_with_nothing_held_against_it() -> None:
    dog, beats = _watchdog(hang=5.0)
    beats.beat()
    dog.check(beats.advance(6.0), heard=True)
    assert dog.kill_reason is not None
    dog.watch()
    assert dog.kill_reason is None
    beats.beat()
    assert dog.check(beats.advance(0.1), heard=True) == [Beat(near(0.1), False)]


def test_checkpoints_are_overdue_after_three_intervals_of_running_and_said_once() -> None:
    dog, beats = _watchdog()
    released = beats.now
    limit = OVERDUE_INTERVALS * 2.0
    assert dog.checkpoint_overdue(beats.advance(limit), released, 2.0) is None
    assert dog.overdue_news(beats.now, released, 2.0) is None
    assert dog.checkpoint_overdue(beats.advance(1.0), released, 2.0) == near(1.0)
    assert dog.overdue_news(beats.now, released, 2.0) == CheckpointsOverdue(None)  # never one
    assert dog.overdue_news(beats.advance(5.0), released, 2.0) is None  # said already
    dog.checkpoint_taken(beats.now)
    assert dog.checkpoint_overdue(beats.advance(limit), released, 2.0) is None
    assert dog.overdue_news(beats.advance(1.0), released, 2.0) == CheckpointsOverdue(
        near(limit + 1.0))


def test_a_node_not_running_released_is_never_overdue() -> None:
    dog, beats = _watchdog()
    assert dog.checkpoint_overdue(beats.advance(3600.0), None, 2.0) is None
    assert dog.overdue_news(beats.now, None, 2.0) is None


def test_a_new_process_may_be_said_overdue_again() -> None:
    dog, beats = _watchdog()
    released = beats.now
    assert dog.overdue_news(beats.advance(10.0), released, 2.0) is not None
    dog.watch()
    assert dog.overdue_news(beats.advance(1.0), released, 2.0) is not None


def test_enforcing_a_finding_says_it_then_signals_the_process() -> None:
    events = FakeEvents(FakeClock())
    child = FakeChild(7, ['node'], {})
    busy: list[InFlight | None] = []

    def applying() -> InFlight | None:
        busy.append(None)
        return None

    enforce(Hung('heartbeat', 5.0, 5.0, signal.SIGUSR1), 'n', 2, child, applying, events)
    assert child.signals == [signal.SIGUSR1] and len(busy) == 1
    assert events.of('hang')[0]['waiting_for'] == 'heartbeat'
    enforce(KillDue(), 'n', 2, child, applying, events)
    enforce(Unheard(11.0), 'n', 2, child, applying, events)
    assert child.signals == [signal.SIGUSR1, signal.SIGKILL, signal.SIGKILL]
    assert events.of('unheard')[0]['beating_s'] == 11.0 and len(busy) == 1


def test_a_reaped_process_hands_its_exit_code_over_from_its_own_thread() -> None:
    child = FakeChild(7, ['node'], {})
    codes: list[int] = []
    reap(child, 'n', codes.append)
    child.finish(3)
    deadline = time.monotonic() + 5.0
    while not codes and time.monotonic() < deadline:
        time.sleep(0.01)
    assert codes == [3]
