"""A node's recoveries one at a time (rory_runtime/supervisor/recoveries.py): which recovery a
crash starts or carries on, and how each ends, over a fake safe state and ring."""

from __future__ import annotations

from pathlib import Path

from fake_supervisor import INPUT, FakeClock, FakeEvents, FakeRing, FakeSafety

from rory_runtime.log import LogEntry, SegmentStore
from rory_runtime.store import CheckpointStore
from rory_runtime.supervisor.recoveries import Recoveries

HOLD, RELEASE = ('hold', 'n'), ('release', 'n')


def _recoveries(tmp_path: Path) -> tuple[Recoveries, FakeSafety, FakeClock]:
    clock, safety = FakeClock(), FakeSafety()
    store = tmp_path / 'store'
    return (Recoveries('n', safety, SegmentStore(store, 'n'), CheckpointStore(store, 'n'),
                       clock, FakeEvents(clock)), safety, clock)


def _ring() -> FakeRing:
    ring = FakeRing()
    ring.ensure([INPUT])
    return ring


def test_a_crash_before_the_release_carries_the_recovery_on(tmp_path: Path) -> None:
    recoveries, safety, clock = _recoveries(tmp_path)
    early = [LogEntry(INPUT.topic, INPUT.msgtype, 5, 5, 7, b'\x00\x01\x00\x00')]
    ring = _ring()
    first = recoveries.crashed(clock(), 1, False, ring, lambda: early)
    assert recoveries.current is first and safety.log == [HOLD]
    assert ring.handed_over == [early]  # R starts from what the ring kept early
    again = recoveries.crashed(clock.advance(1.0), 2, True, ring, lambda: None)
    assert again is first and first.crashes == 2 and safety.log == [HOLD]


def test_a_crash_after_the_release_stops_that_recovery_and_starts_its_own(
    tmp_path: Path
) -> None:
    recoveries, safety, clock = _recoveries(tmp_path)
    first = recoveries.crashed(clock(), 1, False, None, lambda: None)
    first.s4_release()  # released; still relaying (the handover)
    second = recoveries.crashed(clock.advance(1.0), 2, False, None, lambda: None)
    assert second is not first and second.crashes == 1
    assert safety.log == [HOLD, RELEASE, HOLD] and recoveries.current is second


def test_a_recovery_ends_stops_or_is_given_up(tmp_path: Path) -> None:
    recoveries, safety, clock = _recoveries(tmp_path)
    recoveries.start(clock(), 1, None)
    recoveries.end()  # the node exited on its own before S4: the safe state is left
    assert recoveries.current is None and safety.log == [HOLD, RELEASE]
    recoveries.end()
    recoveries.report_gaps()
    recoveries.start(clock(), 2, None)
    recoveries.stop()  # with the supervisor: held, as it was
    assert recoveries.current is not None and safety.log[-1] == HOLD
    recoveries.start(clock(), 3, None)
    recoveries.give_up()
    assert safety.log[-1] == HOLD and safety.held
