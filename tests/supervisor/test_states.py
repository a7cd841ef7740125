"""Tests of the supervisor's per-node state machine."""

from __future__ import annotations

import itertools
import logging
from collections.abc import Callable

import pytest

from rory_runtime.supervisor.states import (
    LOG_PREFIX,
    RECOVERING,
    TRANSITIONS,
    IllegalTransition,
    NodeState,
    NodeStateMachine,
    StateEvent,
)

S = NodeState
LOGGER = 'test.rory.states'
ALLOWED = [(old, new) for old, targets in TRANSITIONS.items() for new in sorted(targets)]
REFUSED = [
    (old, new)
    for old, new in itertools.product(NodeState, NodeState)
    if new not in TRANSITIONS[old]
]


class FakeClock:
    def __init__(self, start: float = 100.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now


def machine(
    clock: Callable[[], float] | None = None,
    listeners: list[Callable[[StateEvent], None]] | None = None,
) -> NodeStateMachine:
    logger = logging.getLogger(LOGGER)
    if clock is None:
        return NodeStateMachine('integrator', logger, listeners=listeners)
    return NodeStateMachine('integrator', logger, clock=clock, listeners=listeners)


def test_transitions_cover_every_state() -> None:
    assert set(TRANSITIONS) == set(NodeState)
    for targets in TRANSITIONS.values():
        assert targets <= set(NodeState)


def test_starts_stopped() -> None:
    assert machine().state is S.STOPPED


@pytest.mark.parametrize(('old', 'new'), ALLOWED, ids=[f'{o}->{n}' for o, n in ALLOWED])
def test_every_edge_in_transitions_is_allowed(old: NodeState, new: NodeState) -> None:
    sm = machine()
    sm.state = old
    event = sm.change_state(new, 'test')
    assert sm.state is new
    assert (event.old, event.new) == (old, new)


@pytest.mark.parametrize(('old', 'new'), REFUSED, ids=[f'{o}->{n}' for o, n in REFUSED])
def test_every_other_pair_is_refused(old: NodeState, new: NodeState) -> None:
    seen: list[StateEvent] = []
    clock = FakeClock()
    sm = machine(clock, [seen.append])
    sm.state = old
    since = sm.since
    clock.now += 5.0
    with pytest.raises(IllegalTransition) as info:
        sm.change_state(new, 'why')
    assert sm.state is old
    assert sm.since == since
    assert seen == []
    assert f'integrator: {old} -> {new}' in str(info.value)


def test_pairs_partition_the_product() -> None:
    assert len(ALLOWED) + len(REFUSED) == len(NodeState) ** 2
    assert (S.RUNNING, S.RUNNING) in REFUSED  # no self loops
    assert (S.STOPPED, S.RUNNING) in REFUSED


def test_normal_life_and_a_recovery_walk_the_model() -> None:
    sm = machine()
    path = [
        S.STARTING, S.ARMING, S.RUNNING, S.CRASHED, S.BACKOFF, S.RESTORING, S.REPLAYING,
        S.RUNNING, S.STOPPING, S.STOPPED,
    ]
    for state in path:
        sm.change_state(state)
    assert sm.state is S.STOPPED


def test_change_state_logs_with_prefix_and_reason(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    sm = machine()
    sm.state = S.RUNNING
    sm.change_state(S.CRASHED, 'killed by SIGKILL')
    assert [r.getMessage() for r in caplog.records] == [
        '[rory] integrator: RUNNING -> CRASHED (killed by SIGKILL)'
    ]
    assert caplog.records[0].levelno == logging.INFO
    assert caplog.records[0].name == LOGGER
    assert LOG_PREFIX == '[rory]'


def test_change_state_without_reason_logs_no_parentheses(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    machine().change_state(S.STARTING)
    assert [r.getMessage() for r in caplog.records] == ['[rory] integrator: STOPPED -> STARTING']


def test_refused_change_is_not_logged(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)
    with pytest.raises(IllegalTransition):
        machine().change_state(S.RUNNING)
    assert caplog.records == []


def test_listeners_get_the_state_event() -> None:
    first: list[StateEvent] = []
    second: list[StateEvent] = []
    clock = FakeClock(10.0)
    sm = machine(clock, [first.append])
    sm.listeners.append(second.append)
    clock.now = 12.5
    returned = sm.change_state(S.STARTING, 'start')
    expected = StateEvent('integrator', S.STOPPED, S.STARTING, 'start', 12.5)
    assert returned == expected
    assert first == [expected]
    assert second == [expected]


def test_listeners_list_is_copied() -> None:
    calls: list[StateEvent] = []
    listeners: list[Callable[[StateEvent], None]] = [calls.append]
    sm = machine(listeners=listeners)
    listeners.clear()
    sm.change_state(S.STARTING)
    assert len(calls) == 1


def test_clock_is_injectable() -> None:
    clock = FakeClock(1000.0)
    sm = machine(clock)
    assert sm.since == 1000.0
    clock.now = 1003.25
    event = sm.change_state(S.STARTING)
    assert sm.since == 1003.25
    assert event.monotonic == 1003.25
    clock.now = 1010.0
    sm.change_state(S.RUNNING)
    assert sm.since == 1010.0


@pytest.mark.parametrize('state', list(NodeState))
def test_recovering_property(state: NodeState) -> None:
    sm = machine()
    sm.state = state
    expected = state in {S.CRASHED, S.BACKOFF, S.RESTORING, S.REPLAYING, S.GATED}
    assert sm.recovering is expected
    assert (state in RECOVERING) is expected
