"""The node's input path (routing.py): what is applied, when, in which order, and never twice;
each topic's phase of the handover (BUFFERED -> LIVE, SHADOW -> HANDOVER -> LIVE).

These drive the runtime's router directly with real CDR bytes; the subscription is a minimal
stand-in (runtime_fakes.py, no DDS participant), since what is tested is the bookkeeping. The
same paths run for real in tests/integration.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from rclpy.qos import QoSProfile
from runtime_fakes import (
    FakeSubscription,
    adopt_numbers,
    deliver_live,
    make_runtime,
    shadow,
)

from rory_runtime import protocol, routing
from rory_runtime.errors import RoryError
from rory_runtime.log import read_segment
from rory_runtime.protocol import Method, Mode
from rory_runtime.routing import IllegalPhaseChange, TopicPhase, transition
from rory_runtime.runtime import NodeRuntime


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
    rt.windows['/numbers'].add((2, 2))  # absorbed by the restored checkpoint
    deliver_live(sub, 5)  # live messages wait during recovery
    for n in (1, 2, 3, 4):
        rt.router.from_shadow(shadow(n))
    assert applied == [1, 3, 4]
    assert rt.stats['duplicates'] == 1


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


def test_a_message_only_the_live_reader_got_is_never_applied_after_later_ones(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sub = adopt_numbers(rt, applied)
    _outage_handover(rt, sub)
    deliver_live(sub, 10)
    # 5 came before 6 from the one publisher; applying it after 6-8 would reorder its stream
    assert applied == [1, 2, 3, 6, 7, 8, 9, 10]
    assert rt.stats['passed_by_relay'] == 1
    assert any('/numbers: 1 message(s) (publication seq 5)' in e for e in rt.reported_errors)


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
    assert rt.stats['passed_by_relay'] == 0


def test_relayed_messages_are_logged_replayed_ones_are_not(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = make_runtime(tmp_path, Mode.RECOVER)
    adopt_numbers(rt, applied)
    rt.router.from_shadow(shadow(1))  # from a sealed segment: already in the log
    rt.open_gates(next_segment=7)
    rt.router.from_shadow(shadow(2, relay=True))  # recorded after RELEASE: only the node logs it
    rt.close()
    logged = list(read_segment(rt.segments.path(7)))
    assert [(e.source_ns, e.seq) for e in logged] == [(2, 2)]
    assert rt.segments.numbers() == [7]


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
    assert any('no relay for /numbers' in e for e in rt.reported_errors)


def test_live_duplicate_of_an_absorbed_message_is_skipped_after_release(
    tmp_path: Path, applied: list[int]
) -> None:
    # e.g. a transient-local publisher re-sending its last sample to the new reader
    rt = make_runtime(tmp_path, Mode.RECOVER, Method.CHECKPOINT)
    sub = adopt_numbers(rt, applied)
    rt.windows['/numbers'].add((9, 9))
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
