"""The output gate (node/gating.py) and the events it runs through the applier: publishers muted
until release; timers held until release, their ticks and clock readings logged before their
callbacks run, and replayed with the readings they took.

Driven by hand through stand-ins of rclpy's entities (runtime_fakes.py, no DDS participant):
the gate alone, and wired in a runtime.
"""

from __future__ import annotations

import threading
from pathlib import Path
from types import SimpleNamespace
from typing import Any

from rclpy.clock import ROSClock
from rclpy.clock_type import ClockType
from rclpy.time import Time
from runtime_fakes import (
    FakeSubscription,
    FakeTimer,
    deliver_live,
    make_runtime,
    shadow,
)
from std_msgs.msg import Int64

from rory_runtime import protocol
from rory_runtime.inflight import InFlightSlot, slot_path
from rory_runtime.log import LogEntry, read_segment
from rory_runtime.node.applier import Applier
from rory_runtime.node.gating import OutputGate
from rory_runtime.node.runtime import NodeRuntime
from rory_runtime.protocol import Method, Mode
from rory_runtime.supervisor.recovery import readings_first


def test_publishers_are_muted_until_release(tmp_path: Path) -> None:
    rt = make_runtime(tmp_path, Mode.RECOVER)
    sent: list[Any] = []

    class _Pub:
        def publish(self, msg: Any) -> None:
            sent.append(msg)

    pub = _Pub()
    rt.adopt_publisher(pub)  # type: ignore[arg-type]
    pub.publish('during replay')
    rt.open_gates(next_segment=1)
    pub.publish('after release')
    assert sent == ['after release']
    assert rt.applier.stats['muted'] == 1


# -- timers and the clock (docs/architecture.md, "Timers and the clock") ----------------------


def _sim_clock(ns: int) -> ROSClock:
    clock = ROSClock()
    clock._set_ros_time_is_active(True)
    _set_sim(clock, ns)
    return clock


def _set_sim(clock: ROSClock, ns: int) -> None:
    clock.set_ros_time_override(Time(nanoseconds=ns, clock_type=ClockType.ROS_TIME))


def _clocked_node(rt: NodeRuntime, clock: ROSClock, seen: list[tuple[str, int, int]]) -> tuple[
        FakeSubscription, FakeTimer]:
    """A node whose subscription and timer both read the clock, twice per message."""

    def on_number(msg: Int64) -> None:
        seen.append(('msg', msg.data, clock.now().nanoseconds))
        seen.append(('again', msg.data, clock.now().nanoseconds))

    def on_tick() -> None:
        seen.append(('tick', 0, clock.now().nanoseconds))

    sub = FakeSubscription('/numbers', on_number)
    rt.adopt_subscription(sub)  # type: ignore[arg-type]
    timer = FakeTimer(on_tick, clock)
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
    rt = make_runtime(tmp_path, Mode.FRESH)
    sub, timer = _clocked_node(rt, clock, live)
    assert timer.canceled  # held until release
    rt.open_gates(next_segment=1)
    timer.reset()
    for n in (1, 2, 3):
        _set_sim(clock, n * 1_000_000)
        deliver_live(sub, n)
        _set_sim(clock, n * 1_000_000 + 500_000)
        timer.callback()
    rt.close()
    logged = list(read_segment(rt.checkpointer.segments.path(1)))
    assert [e.topic for e in logged[:5]] == [
        '/numbers', protocol.CLOCK_RECORD, protocol.CLOCK_RECORD, protocol.TIMER_RECORD,
        protocol.CLOCK_RECORD]
    assert logged[3].seq == 0  # the node's first timer
    assert logged[3].source_ns == 1_500_000  # the tick's time on the timer's clock
    assert rt.applier.stats['ticks'] == 3

    # The next process: sim time has moved on; the replay must not read it.
    replayed: list[tuple[str, int, int]] = []
    clock2 = _sim_clock(999_000_000_000)
    rt2 = make_runtime(tmp_path, Mode.RECOVER, incarnation=3)
    _clocked_node(rt2, clock2, replayed)
    for entry in readings_first(logged):
        rt2.router.from_shadow(_as_shadow(entry, 3))
    assert replayed == live
    assert rt2.applier.stats['ticks_replayed'] == 3 and rt2.applier.stats['replayed'] == 3
    assert rt2.applier.clock is not None and rt2.applier.clock.fallbacks == 0
    assert list(rt2.checkpointer.segments.path(n) for n in rt2.checkpointer.segments.numbers()) == [
        rt.checkpointer.segments.path(1)]  # replay logs nothing again


def test_a_skipped_replayed_message_drops_its_readings_with_it(tmp_path: Path) -> None:
    seen: list[tuple[str, int, int]] = []
    clock = _sim_clock(5)
    rt = make_runtime(tmp_path, Mode.RECOVER)
    _clocked_node(rt, clock, seen)
    rt.applier.windows['/numbers'].add((1, 1))  # message 1 is in the checkpoint already
    reading = protocol.Msg(incarnation=2, flags=0, recv_ns=1_001, source_ns=77,
                           seq=int(ClockType.ROS_TIME), topic=protocol.CLOCK_RECORD, data=b'')
    rt.router.from_shadow(reading)
    rt.router.from_shadow(shadow(1))
    rt.router.from_shadow(shadow(2))  # unrecorded: it came from R
    assert [s[:2] for s in seen] == [('msg', 2), ('again', 2)]
    assert 77 not in [s[2] for s in seen]
    assert rt.applier.clock is not None and rt.applier.clock.fallbacks == 2


def test_without_logging_methods_clocks_and_ticks_are_left_alone(tmp_path: Path) -> None:
    seen: list[tuple[str, int, int]] = []
    clock = _sim_clock(42)
    rt = make_runtime(tmp_path, Mode.FRESH, Method.CHECKPOINT)
    sub, timer = _clocked_node(rt, clock, seen)
    rt.open_gates(next_segment=1)
    deliver_live(sub, 1)
    timer.callback()
    assert rt.applier.clock is None
    assert [s[2] for s in seen] == [42, 42, 42]
    assert rt.checkpointer.segments.numbers() == []


# -- the gate alone ---------------------------------------------------------------------------


def _gate(tmp_path: Path, *, gated: bool = False) -> tuple[OutputGate, list[str]]:
    errors: list[str] = []
    segments = SimpleNamespace(writer=None, segment=lambda: None)
    applier = Applier(lock=threading.RLock(), logs=False, quarantined=frozenset(),
                      inflight=InFlightSlot(slot_path(tmp_path, 'n'), 1),
                      segments=segments, error=errors.append)  # type: ignore[arg-type]
    return OutputGate(applier, gated=gated, error=errors.append), errors


def test_a_held_timer_runs_nothing_until_release_then_runs_as_an_event(tmp_path: Path) -> None:
    gate, _ = _gate(tmp_path)
    ticks: list[int] = []
    timer = FakeTimer(lambda: ticks.append(1), ROSClock())
    gate.adopt_timer(timer)  # type: ignore[arg-type]
    timer.callback()
    assert ticks == [] and gate.applier.progress == 0
    gate.open()
    timer.callback()
    assert ticks == [1] and gate.applier.progress == 1


def test_under_a_release_gate_outputs_open_only_at_open_and_never_before_release(
    tmp_path: Path,
) -> None:
    gate, _ = _gate(tmp_path, gated=True)
    assert not gate.open_outputs()  # OPEN before RELEASE: nothing
    gate.open()
    assert gate.released and not gate.outputs_open
    assert gate.open_outputs() and gate.outputs_open


def test_a_logged_tick_of_a_timer_the_node_never_made_is_an_error_not_a_crash(
    tmp_path: Path,
) -> None:
    gate, errors = _gate(tmp_path)
    gate.replay_event(protocol.Msg(2, 0, 1_000, 1_000, 4, protocol.TIMER_RECORD, b''), [])
    assert errors == ['the log has a tick of timer 4, but the node has no timer 4 (0 made): '
                      'tick skipped']
