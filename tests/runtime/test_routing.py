"""The node's input path (node/routing.py): what is applied, when, in which order, and never twice;
each topic's phase of the handover (BUFFERED -> LIVE, SHADOW -> HANDOVER -> LIVE).

These drive the runtime's router directly with real CDR bytes; the subscription is a minimal
stand-in (runtime_fakes.py, no DDS participant), since what is tested is the bookkeeping. The
same paths run for real in tests/integration.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from rclpy.qos import QoSProfile
from runtime_fakes import (
    FakeSubscription,
    adopt_numbers,
    deliver_live,
    make_runtime,
    shadow,
)

from rory_runtime import protocol
from rory_runtime.errors import RoryError
from rory_runtime.log import read_segment
from rory_runtime.node import routing
from rory_runtime.node.applier import LiveCallback, Window
from rory_runtime.node.event_clock import Reading
from rory_runtime.node.routing import IllegalPhaseChange, Router, TopicPhase, transition
from rory_runtime.node.runtime import NodeRuntime
from rory_runtime.protocol import MessageId, Method, Mode, Status, SwitchedStatus


@pytest.fixture
def applied() -> list[int]:
    return []


def test_a_topic_changes_phase_only_along_the_handover() -> None:
    allowed = {(TopicPhase.BUFFERED, TopicPhase.LIVE), (TopicPhase.SHADOW, TopicPhase.HANDOVER),
               (TopicPhase.HANDOVER, TopicPhase.LIVE)}
    for old in TopicPhase:
        for new in TopicPhase:
            if (old, new) in allowed:
                assert transition('/t', old, new) is new
            else:
                with pytest.raises(IllegalPhaseChange, match=f'/t: {old} -> {new}'):
                    transition('/t', old, new)


def test_a_recovered_topic_goes_from_the_shadow_topic_through_the_handover_to_live(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.RECOVER)
    adopt_numbers(rt, applied)
    assert rt.router.phase('/numbers') is TopicPhase.SHADOW
    rt.open_gates(next_segment=1)
    assert rt.router.phase('/numbers') is TopicPhase.HANDOVER
    rt.router.switch('/numbers')
    assert rt.router.phase('/numbers') is TopicPhase.LIVE
    with pytest.raises(IllegalPhaseChange, match='/numbers: LIVE -> LIVE'):
        rt.router.switch('/numbers')


def test_a_fresh_topic_waits_buffered_and_one_made_after_release_starts_live(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.FRESH)
    adopt_numbers(rt, applied)
    assert rt.router.phase('/numbers') is TopicPhase.BUFFERED
    rt.open_gates(next_segment=1)
    assert rt.router.phase('/numbers') is TopicPhase.LIVE
    recovered = make_runtime(tmp_path / 'recovered', Mode.RECOVER)
    recovered.open_gates(next_segment=1)
    adopt_numbers(recovered, applied)
    assert recovered.router.phase('/numbers') is TopicPhase.LIVE


def test_fresh_start_buffers_until_release_then_applies_in_receive_order(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.FRESH)
    sub = adopt_numbers(rt, applied)
    for n in (1, 2, 3):
        deliver_live(sub, n)
    assert applied == []  # isolated until the ring is armed
    rt.open_gates(next_segment=1)
    deliver_live(sub, 4)
    assert applied == [1, 2, 3, 4]


def test_recovery_applies_the_shadow_stream_and_skips_what_was_absorbed(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sub = adopt_numbers(rt, applied)
    rt.applier.windows['/numbers'].add((2, 2))  # absorbed by the restored checkpoint
    deliver_live(sub, 5)  # live messages wait during recovery
    for n in (1, 2, 3, 4):
        rt.router.from_shadow(shadow(n))
    assert applied == [1, 3, 4]
    assert rt.applier.stats['duplicates'] == 1


def test_handover_switches_after_confirmations_without_loss_or_repeats(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sub = adopt_numbers(rt, applied)
    for n in (1, 2):
        rt.router.from_shadow(shadow(n))
    rt.open_gates(next_segment=5)
    # live and relayed copies interleave; the live reader runs ahead of the relay
    for n in (3, 4, 5, 6):
        deliver_live(sub, n)
    assert rt.router.phase('/numbers') is TopicPhase.HANDOVER
    for n in (3, 4):
        rt.router.from_shadow(shadow(n, relay=True))
    assert rt.router.phase('/numbers') is TopicPhase.HANDOVER  # two confirmations are not enough
    rt.router.from_shadow(shadow(5, relay=True))
    # switched: the live reader carries the stream
    assert rt.router.phase('/numbers') is TopicPhase.LIVE
    rt.router.from_shadow(shadow(6, relay=True))  # late relay copy: ignored
    deliver_live(sub, 7)
    assert applied == [1, 2, 3, 4, 5, 6, 7]


def test_a_long_recovery_applies_nothing_twice_however_many_live_messages_wait(
    tmp_path: Path, applied: list[int]
) -> None:
    # 50 Hz at depth 10 through a 3 s paced replay: 150 live messages wait while the same
    # messages come through the shadow topic, far more than the window of recent identities
    # holds (depth + 80). At the switch, the early ones have left the window; they were
    # applied all the same and must not be applied again.
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sub = adopt_numbers(rt, applied)
    assert protocol.window_size(rt.router.inputs['/numbers'].spec) < 150
    for n in range(1, 151):
        deliver_live(sub, n)
        rt.router.from_shadow(shadow(n))
    rt.open_gates(next_segment=5)
    for n in range(151, 156):
        deliver_live(sub, n)
    for n in range(151, 156):
        rt.router.from_shadow(shadow(n, relay=True))
    assert rt.router.phase('/numbers') is TopicPhase.LIVE
    deliver_live(sub, 156)
    assert applied == list(range(1, 157))


def _outage_handover(rt: NodeRuntime, sub: FakeSubscription) -> None:
    """A lease-expiring outage during recovery: the ring got 1-3, then nothing until 6; the
    node's live reader was matched again one message earlier and got 5 on."""
    for n in (1, 2, 3):
        rt.router.from_shadow(shadow(n))
    rt.open_gates(next_segment=5)
    for n in (5, 6, 7, 8, 9):
        deliver_live(sub, n)
    for n in (6, 7, 8):
        rt.router.from_shadow(shadow(n, relay=True))
    assert rt.router.phase('/numbers') is TopicPhase.LIVE


def test_a_message_only_the_live_reader_got_is_applied_before_the_relayed_one_after_it(
    tmp_path: Path, applied: list[int]
) -> None:
    # The relay sends in the ring's order, the publisher's: 5, waiting live when 6 came by
    # relay, is one the ring never got. Applied just before 6, it keeps the publisher's order.
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sub = adopt_numbers(rt, applied)
    _outage_handover(rt, sub)
    deliver_live(sub, 10)
    assert applied == [1, 2, 3, 5, 6, 7, 8, 9, 10]
    assert rt.applier.stats['passed_by_relay'] == 0 and not rt.reporter.reported_errors
    rt.close()
    segments = rt.checkpointer.segments
    logged = [e.seq for n in segments.numbers() for e in read_segment(segments.path(n))]
    assert logged == [5, 6, 7, 8, 9, 10]  # applied after release: the node logged each


def test_a_message_the_live_reader_got_after_later_ones_came_by_relay_is_never_applied(
    tmp_path: Path, applied: list[int]
) -> None:
    # The same outage, but 6 came by relay before the live reader delivered 5: applying 5
    # now would apply the publisher's messages out of order. It is left out, and said.
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sub = adopt_numbers(rt, applied)
    for n in (1, 2, 3):
        rt.router.from_shadow(shadow(n))
    rt.open_gates(next_segment=5)
    rt.router.from_shadow(shadow(6, relay=True))
    for n in (5, 6, 7, 8, 9):
        deliver_live(sub, n)
    for n in (7, 8):
        rt.router.from_shadow(shadow(n, relay=True))
    assert rt.router.phase('/numbers') is TopicPhase.LIVE
    deliver_live(sub, 10)
    assert applied == [1, 2, 3, 6, 7, 8, 9, 10]
    assert rt.applier.stats['passed_by_relay'] == 1
    assert any('/numbers: 1 message(s) (publication seq 5)' in e
               for e in rt.reporter.reported_errors)


def test_with_two_publishers_a_message_the_relay_missed_is_still_applied(
    tmp_path: Path, applied: list[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Two publishers' sequence numbers interleave: the live reader's order says nothing of
    # one publisher's message against the other's, so nothing is left out.
    monkeypatch.setattr(FakeSubscription, 'get_publisher_count', lambda self: 2)
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sub = adopt_numbers(rt, applied)
    _outage_handover(rt, sub)
    assert sorted(applied) == [1, 2, 3, 5, 6, 7, 8, 9]
    assert rt.applier.stats['passed_by_relay'] == 0


def test_relayed_messages_are_logged_replayed_ones_are_not(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.RECOVER)
    adopt_numbers(rt, applied)
    rt.router.from_shadow(shadow(1))  # from a sealed segment: already in the log
    rt.open_gates(next_segment=7)
    rt.router.from_shadow(shadow(2, relay=True))  # recorded after RELEASE: only the node logs it
    rt.close()
    logged = list(read_segment(rt.checkpointer.segments.path(7)))
    assert [(e.source_ns, e.seq) for e in logged] == [(2, 2)]
    assert rt.checkpointer.segments.numbers() == [7]


def test_silent_relay_switches_the_topic_to_live_instead_of_stalling(
    tmp_path: Path, applied: list[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(routing, 'RELAY_SILENCE_NS', 0)
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sub = adopt_numbers(rt, applied)
    rt.router.from_shadow(shadow(1))
    rt.open_gates(next_segment=3)
    deliver_live(sub, 1)  # already applied from the shadow topic: skipped when drained
    deliver_live(sub, 2)
    assert rt.router.phase('/numbers') is TopicPhase.LIVE
    assert applied == [1, 2]
    assert any('no relay for /numbers' in e for e in rt.reporter.reported_errors)


# -- the handover after a link outage longer than the DDS lease (issue 35) ---------------------
#
# The publisher matches the node's live reader and the supervisor's ring again each on its own
# schedule. These drive a Router alone, with a clock of their own, through each order.


class _Clock:
    """Wall-clock nanoseconds that move only when told."""

    def __init__(self) -> None:
        self.ns = 1_700_000_000_000_000_000

    def __call__(self) -> int:
        return self.ns

    def advance(self, seconds: float) -> None:
        self.ns += round(seconds * 1e9)


@dataclass
class _Bench:
    """A Router of a recovering node and what it did: messages applied (number, logged),
    errors, statuses."""

    router: Router
    sub: FakeSubscription
    clock: _Clock
    applied: list[tuple[int, bool]] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    statuses: list[Status] = field(default_factory=list)

    def live(self, *numbers: int) -> None:
        for n in numbers:
            deliver_live(self.sub, n)

    def relay(self, *numbers: int) -> None:
        for n in numbers:
            self.router.from_shadow(shadow(n, relay=True))

    def quiet(self, seconds: float, *, alive: bool, live: list[int] | None = None) -> None:
        """``seconds`` pass in steps of the relay's keepalive period, with an ALIVE at each
        step if ``alive``, and one of ``live`` delivered per step while any is left."""
        waiting = list(live or [])
        steps = round(seconds / protocol.RELAY_KEEPALIVE_S)
        for _ in range(steps):
            self.clock.advance(protocol.RELAY_KEEPALIVE_S)
            if alive:
                self.router.relay_alive()
            if waiting:
                self.live(waiting.pop(0))

    @property
    def numbers(self) -> list[int]:
        return [n for n, _ in self.applied]

    @property
    def phase(self) -> TopicPhase:
        return self.router.phase('/numbers')


class _Applier:
    """What the router hands messages to (``routing.Applying``): records each message applied
    (number, logged) and keeps the windows and counters the router reads."""

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.windows: dict[str, Window] = {}
        self.stats = dict.fromkeys(('applied', 'replayed', 'duplicates', 'quarantined',
                                    'passed_by_relay'), 0)
        self.quarantined: frozenset[tuple[str, MessageId]] = frozenset()
        self.applied: list[tuple[int, bool]] = []

    def apply(self, inp: routing.Input, raw: bytes, info: dict[str, Any], ident: MessageId,
              readings: Iterable[Reading] = (), *, log: bool) -> None:
        self.applied.append((ident[1], log))
        self.windows[inp.topic].add(ident)

    def live_path(self, inp: routing.Input) -> LiveCallback:
        def live(raw: bytes, info: dict[str, Any]) -> None:
            ident = protocol.message_id(info)
            if ident in self.windows[inp.topic]:
                self.stats['duplicates'] += 1
            else:
                self.apply(inp, raw, info, ident, log=True)

        return live


def _bench(*, replayed: tuple[int, ...] = (1, 2, 3)) -> _Bench:
    """Released after replaying ``replayed``: /numbers in HANDOVER."""
    clock = _Clock()
    applier = _Applier()
    errors: list[str] = []
    statuses: list[Status] = []
    router = Router(recovering=True, applier=applier, replay_event=lambda msg, readings: None,
                    error=errors.append, status=statuses.append, clock=clock)
    sub = FakeSubscription('/numbers', lambda msg: None)
    router.adopt(sub, released=False)  # type: ignore[arg-type]
    for n in replayed:
        router.from_shadow(shadow(n))
    router.release()
    assert router.phase('/numbers') is TopicPhase.HANDOVER
    return _Bench(router, sub, clock, applier.applied, errors, statuses)


def test_the_live_reader_back_first_waits_for_a_relay_that_is_alive_then_loses_nothing_it_got(
) -> None:
    # Link down: nothing for 4 s; the relay has nothing to relay and says it is alive. Then
    # the node's reader is matched again first and gets 7-10 while the ring has nothing, for
    # 3 s: longer than RELAY_SILENCE_NS, yet no switch, since the relay is alive. Then the ring
    # is matched again at 9: 7 and 8 reached only the live reader and are applied before 9.
    b = _bench()
    b.quiet(4.0, alive=True)
    b.quiet(3.0, alive=True, live=[7, 8, 9, 10])
    assert routing.RELAY_SILENCE_NS < 3.0e9
    assert b.phase is TopicPhase.HANDOVER and b.errors == [] and b.numbers == [1, 2, 3]
    b.relay(9)
    assert b.applied[3:] == [(7, True), (8, True), (9, True)]  # live ones logged, in order
    b.relay(10)
    b.live(11)
    b.relay(11)  # 9, 10, 11 came both ways: switched
    assert b.phase is TopicPhase.LIVE
    b.live(12)
    assert b.numbers == [1, 2, 3, 7, 8, 9, 10, 11, 12]
    assert b.statuses == [SwitchedStatus(topic='/numbers', passed_by_relay=(), live_only=(7, 8))]
    assert b.errors == []


def test_the_ring_back_first_relays_in_order_and_nothing_is_applied_from_live_alone() -> None:
    # The other order: the ring is matched again at 5, the live reader at 7, and the live
    # copies run ahead of the relay. Nothing the relay will deliver is taken from live early.
    b = _bench()
    b.quiet(4.0, alive=True)
    b.relay(5)
    b.live(7, 8)
    b.relay(6)
    assert b.numbers == [1, 2, 3, 5, 6]
    b.relay(7, 8)
    b.live(9)
    b.relay(9)
    assert b.phase is TopicPhase.LIVE
    assert b.numbers == [1, 2, 3, 5, 6, 7, 8, 9]
    assert b.statuses == [SwitchedStatus(topic='/numbers', passed_by_relay=(), live_only=())]


def test_a_live_message_older_than_what_was_applied_is_never_applied_before_a_relayed_one(
) -> None:
    # 3 never came through the shadow topic (the ring dropped it as never delivered to the
    # old process), and a transient-local publisher sends it to the new reader: it is older
    # than 4, applied already, so it waits for the switch, which leaves it out.
    b = _bench(replayed=(1, 2, 4, 5))
    b.live(3, 6, 7)
    b.relay(6, 7)
    assert b.numbers == [1, 2, 4, 5, 6, 7]
    b.live(8)
    b.relay(8)
    assert b.phase is TopicPhase.LIVE and b.numbers == [1, 2, 4, 5, 6, 7, 8]
    assert b.statuses == [SwitchedStatus(topic='/numbers', passed_by_relay=(3,), live_only=())]


def test_a_relay_truly_silent_for_longer_than_the_silence_bound_is_taken_for_gone() -> None:
    # No ALIVE, no message: the supervisor died. The node switches rather than stall, and
    # says what it can tell it missed (4-6, between the last applied and the first live).
    # 7 is applied too: none of the live messages waiting ever came by the shadow topic, and
    # the switch used to leave out all of them but the last as passed by the relay.
    b = _bench()
    b.quiet(1.5, alive=False)
    b.live(7)
    assert b.phase is TopicPhase.HANDOVER
    b.quiet(1.0, alive=False)
    b.live(8)
    assert b.phase is TopicPhase.LIVE
    assert b.numbers == [1, 2, 3, 7, 8]
    (error,) = b.errors
    assert error.startswith('no relay for /numbers; switching it to live unconfirmed: '
                            "nothing from the supervisor's relay for 2.5 s")
    assert error.endswith('publication seq 4-6 never reached this node')


def test_an_alive_relay_that_relays_nothing_of_a_topic_is_waited_for_only_so_long() -> None:
    # The relay is alive, but the ring is never matched again with the publisher: the topic
    # switches once its live messages have waited RELAY_WAIT_NS, with an error naming it.
    b = _bench()
    wait_s = routing.RELAY_WAIT_NS / 1e9
    b.live(7)
    b.quiet(wait_s, alive=True, live=list(range(8, 8 + round(wait_s / 0.5))))
    assert b.phase is TopicPhase.HANDOVER and b.errors == []  # 10 s since 7 came, not more
    b.quiet(0.5, alive=True)
    b.live(100)
    assert b.phase is TopicPhase.LIVE
    (error,) = b.errors
    assert error.startswith('no relay for /numbers; switching it to live unconfirmed: the '
                            'relay is alive but relayed nothing of it while its live messages '
                            'waited 10.5 s')
    assert error.endswith('publication seq 4-6 never reached this node')
    assert b.numbers[:4] == [1, 2, 3, 7] and b.numbers[-1] == 100


def test_live_duplicate_of_an_absorbed_message_is_skipped_after_release(
    tmp_path: Path, applied: list[int]
) -> None:
    # e.g. a transient-local publisher re-sending its last sample to the new reader
    rt = make_runtime(tmp_path, Mode.RECOVER, Method.CHECKPOINT)
    sub = adopt_numbers(rt, applied)
    rt.applier.windows['/numbers'].add((9, 9))
    rt.open_gates(next_segment=1)
    deliver_live(sub, 9)
    deliver_live(sub, 10)
    assert applied == [10]


def test_a_second_subscription_to_the_same_topic_is_refused_clearly(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.FRESH)
    adopt_numbers(rt, applied)
    with pytest.raises(RoryError, match='subscribes twice to /numbers'):
        adopt_numbers(rt, applied)


@pytest.mark.ros
def test_the_shadow_subscription_is_retired_only_once_nothing_can_come_on_it(
    tmp_path: Path, applied: list[int], ros_domain: int
) -> None:
    # After the handover the shadow subscription would only lengthen every executor wait; it
    # goes at the first tick after release with every topic live and no relayed message
    # waiting for a subscription, and not before.
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from std_msgs.msg import UInt8MultiArray

    context = Context()
    rclpy.init(context=context, domain_id=ros_domain)
    try:
        node = Node('shadow_retire', context=context)
        rt = make_runtime(tmp_path, Mode.RECOVER)
        sub = adopt_numbers(rt, applied)
        shadow_sub = node.create_subscription(UInt8MultiArray, '/rory/n/replay',
                                              lambda m: None, QoSProfile(depth=10))
        rt.node, rt.shadow_subscription = node, shadow_sub

        def present() -> bool:
            return any(s is shadow_sub for s in node.subscriptions)

        rt.router.from_shadow(shadow(1))
        rt.retire_shadow()
        assert present()  # not released yet
        rt.open_gates(next_segment=3)
        rt.retire_shadow()
        assert present()  # still taken from the relay
        assert rt.router.phase('/numbers') is TopicPhase.HANDOVER
        rt.router.orphans['/later'] = [shadow(9)]
        rt.router.switch('/numbers')
        rt.retire_shadow()
        assert present()  # a relayed message still waits for its subscription
        rt.router.orphans.clear()
        rt.retire_shadow()
        assert not present() and rt.shadow_subscription is None
        rt.retire_shadow()  # idempotent
        deliver_live(sub, 2)
        assert applied == [1, 2]
    finally:
        context.try_shutdown()
