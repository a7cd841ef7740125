"""The release gate on its own (supervisor/gate.py): a fake clock, OPEN sends counted."""

from __future__ import annotations

from fake_supervisor import RELEASED_STATS, FakeClock

from rory_runtime.protocol import ReleasedStatus
from rory_runtime.supervisor.config import ReleaseGate
from rory_runtime.supervisor.gate import SYNC_PERIOD, Gate
from rory_runtime.supervisor.states import NodeState

STATS = ReleasedStatus(**RELEASED_STATS)


class Opens:
    def __init__(self) -> None:
        self.sent = 0

    def __call__(self) -> None:
        self.sent += 1


def _gate(timeout: float | None = None,
          on_timeout: str = 'give_up') -> tuple[Gate, FakeClock, Opens]:
    clock, opens = FakeClock(), Opens()
    gate = Gate('n', ReleaseGate(timeout, on_timeout), '/rory/n/release', clock, opens)
    return gate, clock, opens


def test_entering_holds_the_stats_and_says_what_opens_it() -> None:
    gate, clock, opens = _gate(timeout=5.0)
    reason = gate.enter(STATS)
    assert reason == ('caught up; outputs muted and the safe state held until /rory/n/release '
                      'is called, give up after 5 s')
    assert gate.held is STATS and gate.deadline == clock() + 5.0 and opens.sent == 0


def test_a_call_at_the_gate_opens_it_and_open_is_sent_again_until_opened() -> None:
    gate, clock, opens = _gate()
    gate.enter(STATS)
    assert gate.on_call(NodeState.GATED) == (True, 'n: released')
    assert opens.sent == 1 and gate.reason == '/rory/n/release called'
    gate.on_call(NodeState.GATED)  # opened once
    assert opens.sent == 1
    assert gate.tick(clock.advance(SYNC_PERIOD / 2)) is None and opens.sent == 1
    assert gate.tick(clock.advance(SYNC_PERIOD)) is None and opens.sent == 2
    assert gate.opened() is STATS and gate.held is None
    clock.advance(0.425)
    assert gate.finish() == (500.0, '/rory/n/release called')
    assert (gate.since, gate.deadline, gate.called, gate.open_sent, gate.reason) == (
        None, None, False, False, '')


def test_a_call_during_the_recovery_is_remembered_and_a_call_without_one_refused() -> None:
    gate, _, opens = _gate()
    assert gate.on_call(NodeState.REPLAYING) == (
        True, 'n: replaying; released as soon as it has caught up')
    assert gate.called and opens.sent == 0
    assert gate.on_call(NodeState.RUNNING) == (False, 'n: RUNNING, no recovery waits for release')


def test_at_its_timeout_it_opens_or_says_why_the_supervisor_gives_up() -> None:
    gate, clock, opens = _gate(timeout=2.0, on_timeout='release')
    gate.enter(STATS)
    assert gate.tick(clock.advance(1.9)) is None and opens.sent == 0
    assert gate.tick(clock.advance(0.1)) is None and opens.sent == 1
    assert gate.reason == 'no call within 2 s; on_timeout: release'
    gate, clock, opens = _gate(timeout=2.0)
    gate.enter(STATS)
    assert gate.tick(clock.advance(2.0)) == ('no call on /rory/n/release within 2 s; '
                                             'on_timeout: give_up; the safe state is held')
    assert opens.sent == 0


def test_finish_without_a_gate_entered_has_no_time() -> None:
    gate, _, _ = _gate()
    assert gate.finish() == (None, None)
