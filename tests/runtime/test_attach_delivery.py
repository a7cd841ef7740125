"""The node-side delivery rules: what is applied, when, in which order, and never twice.

These drive NodeRuntime's delivery methods directly with real CDR bytes; the subscription is a
minimal stand-in (no DDS participant), since what is tested is the runtime's bookkeeping. The
same paths run for real in tests/integration.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from rclpy.clock import Clock, ROSClock
from rclpy.clock_type import ClockType
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message
from rclpy.time import Time
from std_msgs.msg import Int64

from rory_runtime import attach, protocol
from rory_runtime.attach import CheckpointSpec, NodeRuntime, RuntimeEnv
from rory_runtime.log import LogEntry, read_segment
from rory_runtime.protocol import FLAG_RELAY, Method, Mode
from rory_runtime.supervisor.recovery import readings_first


@dataclass
class _Sub:
    """What adopt_subscription reads from an rclpy Subscription."""

    topic_name: str
    callback: Callable[..., Any]
    msg_type: type = Int64
    raw: bool = False
    qos_profile: QoSProfile = field(default_factory=lambda: QoSProfile(depth=10))

    def get_publisher_count(self) -> int:
        return 1


def _runtime(tmp_path: Path, mode: Mode, method: Method = Method.RORY) -> NodeRuntime:
    env = RuntimeEnv(
        node_id='n', store=tmp_path, incarnation=2, method=method, mode=mode, interval=2.0
    )
    return NodeRuntime(CheckpointSpec(('x',), 'sha256:0'), env)


def _info(n: int) -> dict[str, Any]:
    # identity = (source timestamp, sequence): message n has both equal to n
    return {
        'source_timestamp': n,
        'received_timestamp': 1_000 + n,
        'publication_sequence_number': n,
        'reception_sequence_number': None,
    }


def _cdr(n: int) -> bytes:
    return bytes(serialize_message(Int64(data=n)))


def _shadow(n: int, *, relay: bool = False) -> protocol.Msg:
    return protocol.Msg(
        incarnation=2, flags=FLAG_RELAY if relay else 0, recv_ns=1_000 + n, source_ns=n, seq=n,
        topic='/numbers', data=_cdr(n),
    )


@pytest.fixture
def applied() -> list[int]:
    return []


def _adopt(rt: NodeRuntime, applied: list[int]) -> _Sub:
    sub = _Sub('/numbers', lambda msg: applied.append(msg.data))
    rt.adopt_subscription(sub)  # type: ignore[arg-type]
    return sub


def _live(sub: _Sub, n: int) -> None:
    sub.callback(_cdr(n), _info(n))


def test_fresh_start_buffers_until_release_then_applies_in_receive_order(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = _runtime(tmp_path, Mode.FRESH)
    sub = _adopt(rt, applied)
    for n in (1, 2, 3):
        _live(sub, n)
    assert applied == []  # isolated until the ring is armed
    rt._open_gates(next_segment=1)
    _live(sub, 4)
    assert applied == [1, 2, 3, 4]


def test_recovery_applies_the_shadow_stream_and_skips_what_was_absorbed(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = _runtime(tmp_path, Mode.RECOVER)
    sub = _adopt(rt, applied)
    rt.windows['/numbers'].add((2, 2))  # absorbed by the restored checkpoint
    _live(sub, 5)  # live messages wait during recovery
    for n in (1, 2, 3, 4):
        rt._from_shadow(_shadow(n))
    assert applied == [1, 3, 4]
    assert rt.stats['duplicates'] == 1


def test_handover_switches_after_confirmations_without_loss_or_repeats(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = _runtime(tmp_path, Mode.RECOVER)
    sub = _adopt(rt, applied)
    for n in (1, 2):
        rt._from_shadow(_shadow(n))
    rt._open_gates(next_segment=5)
    # live and relayed copies interleave; the live reader runs ahead of the relay
    for n in (3, 4, 5, 6):
        _live(sub, n)
    assert '/numbers' in rt.shadow_topics
    for n in (3, 4):
        rt._from_shadow(_shadow(n, relay=True))
    assert '/numbers' in rt.shadow_topics  # two confirmations are not enough
    rt._from_shadow(_shadow(5, relay=True))
    assert '/numbers' not in rt.shadow_topics  # switched: the live reader carries the stream
    rt._from_shadow(_shadow(6, relay=True))  # late relay copy: ignored
    _live(sub, 7)
    assert applied == [1, 2, 3, 4, 5, 6, 7]


def test_a_long_recovery_applies_nothing_twice_however_many_live_messages_wait(
    tmp_path: Path, applied: list[int]
) -> None:
    # 50 Hz at depth 10 through a 3 s paced replay: 150 live messages wait while the same
    # messages come through the shadow topic, far more than the window of recent identities
    # holds (depth + 80). At the switch, the early ones have left the window; they were
    # applied all the same and must not be applied again.
    rt = _runtime(tmp_path, Mode.RECOVER)
    sub = _adopt(rt, applied)
    assert protocol.window_size(rt.inputs['/numbers'].spec) < 150
    for n in range(1, 151):
        _live(sub, n)
        rt._from_shadow(_shadow(n))
    rt._open_gates(next_segment=5)
    for n in range(151, 156):
        _live(sub, n)
    for n in range(151, 156):
        rt._from_shadow(_shadow(n, relay=True))
    assert '/numbers' not in rt.shadow_topics
    _live(sub, 156)
    assert applied == list(range(1, 157))


def _outage_handover(rt: NodeRuntime, sub: _Sub) -> None:
    """A lease-expiring outage during recovery: the ring got 1-3, then nothing until 6; the
    node's live reader was matched again one message earlier and got 5 on."""
    for n in (1, 2, 3):
        rt._from_shadow(_shadow(n))
    rt._open_gates(next_segment=5)
    for n in (5, 6, 7, 8, 9):
        _live(sub, n)
    for n in (6, 7, 8):
        rt._from_shadow(_shadow(n, relay=True))
    assert '/numbers' not in rt.shadow_topics


def test_a_message_only_the_live_reader_got_is_never_applied_after_later_ones(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = _runtime(tmp_path, Mode.RECOVER)
    sub = _adopt(rt, applied)
    _outage_handover(rt, sub)
    _live(sub, 10)
    # 5 came before 6 from the one publisher; applying it after 6-8 would reorder its stream
    assert applied == [1, 2, 3, 6, 7, 8, 9, 10]
    assert rt.stats['passed_by_relay'] == 1
    assert any('/numbers: 1 message(s) (publication seq 5)' in e for e in rt.reported_errors)


def test_with_two_publishers_a_message_the_relay_missed_is_still_applied(
    tmp_path: Path, applied: list[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    # Two publishers' sequence numbers interleave: the live reader's order says nothing of
    # one publisher's message against the other's, so nothing is left out.
    monkeypatch.setattr(_Sub, 'get_publisher_count', lambda self: 2)
    rt = _runtime(tmp_path, Mode.RECOVER)
    sub = _adopt(rt, applied)
    _outage_handover(rt, sub)
    assert sorted(applied) == [1, 2, 3, 5, 6, 7, 8, 9]
    assert rt.stats['passed_by_relay'] == 0


def test_relayed_messages_are_logged_replayed_ones_are_not(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = _runtime(tmp_path, Mode.RECOVER)
    _adopt(rt, applied)
    rt._from_shadow(_shadow(1))  # from a sealed segment: already in the log
    rt._open_gates(next_segment=7)
    rt._from_shadow(_shadow(2, relay=True))  # recorded after RELEASE: only the node logs it
    rt.close()
    logged = list(read_segment(rt.segments.path(7)))
    assert [(e.source_ns, e.seq) for e in logged] == [(2, 2)]
    assert rt.segments.numbers() == [7]


def test_silent_relay_switches_the_topic_to_live_instead_of_stalling(
    tmp_path: Path, applied: list[int], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(attach, 'RELAY_SILENCE_NS', 0)
    rt = _runtime(tmp_path, Mode.RECOVER)
    sub = _adopt(rt, applied)
    rt._from_shadow(_shadow(1))
    rt._open_gates(next_segment=3)
    _live(sub, 1)  # already applied from the shadow topic: skipped when drained
    _live(sub, 2)
    assert '/numbers' not in rt.shadow_topics
    assert applied == [1, 2]
    assert any('no relay for /numbers' in e for e in rt.reported_errors)


def test_live_duplicate_of_an_absorbed_message_is_skipped_after_release(
    tmp_path: Path, applied: list[int]
) -> None:
    # e.g. a transient-local publisher re-sending its last sample to the new reader
    rt = _runtime(tmp_path, Mode.RECOVER, Method.CHECKPOINT)
    sub = _adopt(rt, applied)
    rt.windows['/numbers'].add((9, 9))
    rt._open_gates(next_segment=1)
    _live(sub, 9)
    _live(sub, 10)
    assert applied == [10]


def test_publishers_are_muted_until_release(tmp_path: Path) -> None:
    rt = _runtime(tmp_path, Mode.RECOVER)
    sent: list[Any] = []

    class _Pub:
        def publish(self, msg: Any) -> None:
            sent.append(msg)

    pub = _Pub()
    rt.adopt_publisher(pub)  # type: ignore[arg-type]
    pub.publish('during replay')
    rt._open_gates(next_segment=1)
    pub.publish('after release')
    assert sent == ['after release']
    assert rt.stats['muted'] == 1


def test_a_second_subscription_to_the_same_topic_is_refused_clearly(
    tmp_path: Path, applied: list[int]
) -> None:
    rt = _runtime(tmp_path, Mode.FRESH)
    _adopt(rt, applied)
    with pytest.raises(attach.RoryError, match='subscribes twice to /numbers'):
        _adopt(rt, applied)


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
        rt = _runtime(tmp_path, Mode.RECOVER)
        sub = _adopt(rt, applied)
        shadow = node.create_subscription(UInt8MultiArray, '/rory/n/replay', lambda m: None,
                                          QoSProfile(depth=10))
        rt.node, rt._shadow_sub = node, shadow

        def present() -> bool:
            return any(s is shadow for s in node.subscriptions)

        rt._from_shadow(_shadow(1))
        rt._retire_shadow()
        assert present()  # not released yet
        rt._open_gates(next_segment=3)
        rt._retire_shadow()
        assert present() and '/numbers' in rt.shadow_topics  # still taken from the relay
        rt.orphans['/later'] = [_shadow(9)]
        rt._switch('/numbers')
        rt._retire_shadow()
        assert present()  # a relayed message still waits for its subscription
        rt.orphans.clear()
        rt._retire_shadow()
        assert not present() and rt._shadow_sub is None
        rt._retire_shadow()  # idempotent
        _live(sub, 2)
        assert applied == [1, 2]
    finally:
        context.try_shutdown()


# -- timers and the clock (docs/architecture.md, "Timers and the clock") ----------------------


@dataclass
class _Timer:
    """What adopt_timer and a tick read from an rclpy Timer."""

    callback: Callable[[], Any]
    clock: Clock
    canceled: bool = False

    def is_canceled(self) -> bool:
        return self.canceled

    def cancel(self) -> None:
        self.canceled = True

    def reset(self) -> None:
        self.canceled = False


def _sim_clock(ns: int) -> ROSClock:
    clock = ROSClock()
    clock._set_ros_time_is_active(True)
    _set_sim(clock, ns)
    return clock


def _set_sim(clock: ROSClock, ns: int) -> None:
    clock.set_ros_time_override(Time(nanoseconds=ns, clock_type=ClockType.ROS_TIME))


def _clocked_node(rt: NodeRuntime, clock: ROSClock, seen: list[tuple[str, int, int]]) -> tuple[
        _Sub, _Timer]:
    """A node whose subscription and timer both read the clock, twice per message."""

    def on_number(msg: Int64) -> None:
        seen.append(('msg', msg.data, clock.now().nanoseconds))
        seen.append(('again', msg.data, clock.now().nanoseconds))

    def on_tick() -> None:
        seen.append(('tick', 0, clock.now().nanoseconds))

    sub = _Sub('/numbers', on_number)
    rt.adopt_subscription(sub)  # type: ignore[arg-type]
    timer = _Timer(on_tick, clock)
    rt.adopt_timer(timer)  # type: ignore[arg-type]
    return sub, timer


def _as_shadow(entry: LogEntry, incarnation: int) -> protocol.Msg:
    return protocol.Msg(incarnation=incarnation, flags=0, recv_ns=entry.recv_ns,
                        source_ns=entry.source_ns, seq=entry.seq, topic=entry.topic,
                        data=entry.data)


def test_ticks_and_clock_readings_are_logged_and_replay_in_order_with_the_recorded_times(
    tmp_path: Path,
) -> None:
    live: list[tuple[str, int, int]] = []
    clock = _sim_clock(10_000)
    rt = _runtime(tmp_path, Mode.FRESH)
    sub, timer = _clocked_node(rt, clock, live)
    assert timer.canceled  # held until release
    rt._open_gates(next_segment=1)
    timer.reset()
    for n in (1, 2, 3):
        _set_sim(clock, n * 1_000_000)
        _live(sub, n)
        _set_sim(clock, n * 1_000_000 + 500_000)
        timer.callback()
    rt.close()
    logged = list(read_segment(rt.segments.path(1)))
    assert [e.topic for e in logged[:5]] == [
        '/numbers', protocol.CLOCK_RECORD, protocol.CLOCK_RECORD, protocol.TIMER_RECORD,
        protocol.CLOCK_RECORD]
    assert logged[3].seq == 0  # the node's first timer
    assert logged[3].source_ns == 1_500_000  # the tick's time on the timer's clock
    assert rt.stats['ticks'] == 3

    # The next process: sim time has moved on; the replay must not read it.
    replayed: list[tuple[str, int, int]] = []
    clock2 = _sim_clock(999_000_000_000)
    rt2 = NodeRuntime(CheckpointSpec(('x',), 'sha256:0'), RuntimeEnv(
        node_id='n', store=tmp_path, incarnation=3, method=Method.RORY, mode=Mode.RECOVER,
        interval=2.0))
    _clocked_node(rt2, clock2, replayed)
    for entry in readings_first(logged):
        rt2._from_shadow(_as_shadow(entry, 3))
    assert replayed == live
    assert rt2.stats['ticks_replayed'] == 3 and rt2.stats['replayed'] == 3
    assert rt2.clock is not None and rt2.clock.fallbacks == 0
    assert list(rt2.segments.path(n) for n in rt2.segments.numbers()) == [
        rt.segments.path(1)]  # replay logs nothing again


def test_a_skipped_replayed_message_drops_its_readings_with_it(tmp_path: Path) -> None:
    seen: list[tuple[str, int, int]] = []
    clock = _sim_clock(5)
    rt = _runtime(tmp_path, Mode.RECOVER)
    _clocked_node(rt, clock, seen)
    rt.windows['/numbers'].add((1, 1))  # message 1 is in the checkpoint already
    reading = protocol.Msg(incarnation=2, flags=0, recv_ns=1_001, source_ns=77,
                           seq=int(ClockType.ROS_TIME), topic=protocol.CLOCK_RECORD, data=b'')
    rt._from_shadow(reading)
    rt._from_shadow(_shadow(1))
    rt._from_shadow(_shadow(2))  # unrecorded: it came from R
    assert [s[:2] for s in seen] == [('msg', 2), ('again', 2)]
    assert 77 not in [s[2] for s in seen]
    assert rt.clock is not None and rt.clock.fallbacks == 2


def test_without_logging_methods_clocks_and_ticks_are_left_alone(tmp_path: Path) -> None:
    seen: list[tuple[str, int, int]] = []
    clock = _sim_clock(42)
    rt = _runtime(tmp_path, Mode.FRESH, Method.CHECKPOINT)
    sub, timer = _clocked_node(rt, clock, seen)
    rt._open_gates(next_segment=1)
    _live(sub, 1)
    timer.callback()
    assert rt.clock is None
    assert [s[2] for s in seen] == [42, 42, 42]
    assert rt.segments.numbers() == []
