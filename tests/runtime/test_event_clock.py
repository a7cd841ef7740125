"""The node's clocks inside events: recorded while live, read back in order in replay."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
from rclpy.clock import Clock, ROSClock
from rclpy.clock_type import ClockType
from rclpy.time import Time

from rory_runtime.node import event_clock
from rory_runtime.node.event_clock import MAX_READINGS_PER_EVENT, EventClock, Reading


class _Recorder:
    def __init__(self) -> None:
        self.readings: list[Reading] = []
        self.unrecorded = 0

    def record(self, reading: Reading) -> None:
        self.readings.append(reading)

    def on_unrecorded(self) -> None:
        self.unrecorded += 1


@pytest.fixture
def recorder() -> _Recorder:
    return _Recorder()


@pytest.fixture
def events(recorder: _Recorder) -> Iterator[EventClock]:
    event_clock.install()
    clock = EventClock(recorder.record, recorder.on_unrecorded)
    yield clock
    clock.end()


def _ros_clock_with(ns: int) -> ROSClock:
    """A ROS clock driven by a /clock-like override (what use_sim_time does)."""
    clock = ROSClock()
    clock._set_ros_time_is_active(True)
    clock.set_ros_time_override(Time(nanoseconds=ns, clock_type=ClockType.ROS_TIME))
    return clock


def test_outside_an_event_clocks_read_live_and_nothing_is_recorded(
    events: EventClock, recorder: _Recorder
) -> None:
    before = time.time_ns()
    now = Clock(clock_type=ClockType.SYSTEM_TIME).now().nanoseconds
    assert before <= now <= time.time_ns()
    assert recorder.readings == []


def test_a_live_event_records_every_reading_in_order_and_returns_it(
    events: EventClock, recorder: _Recorder
) -> None:
    sim = _ros_clock_with(5_000_000_000)
    steady = Clock(clock_type=ClockType.STEADY_TIME)
    events.begin_live()
    first = sim.now()
    second = steady.now()
    sim.set_ros_time_override(Time(nanoseconds=5_020_000_000, clock_type=ClockType.ROS_TIME))
    third = sim.now()
    events.end()
    assert [r.clock_type for r in recorder.readings] == [
        ClockType.ROS_TIME, ClockType.STEADY_TIME, ClockType.ROS_TIME]
    assert [r.value_ns for r in recorder.readings] == [
        first.nanoseconds, second.nanoseconds, third.nanoseconds]
    assert first.nanoseconds == 5_000_000_000 and third.nanoseconds == 5_020_000_000
    assert first.clock_type == ClockType.ROS_TIME


def test_a_replayed_event_reads_what_it_recorded_not_the_live_clock(
    events: EventClock,
) -> None:
    sim = _ros_clock_with(99_000_000_000)  # live sim time has moved on since the crash
    recorded = [Reading(ClockType.ROS_TIME, 5_000_000_000, 1_000),
                Reading(ClockType.ROS_TIME, 5_020_000_000, 1_010)]
    events.begin_replay(1_000, recorded)
    assert sim.now().nanoseconds == 5_000_000_000
    assert sim.now().nanoseconds == 5_020_000_000
    events.end()
    assert sim.now().nanoseconds == 99_000_000_000  # after the event: live again
    assert events.fallbacks == 0


def test_a_replayed_event_without_a_recording_reads_its_own_time_with_the_last_offset(
    events: EventClock,
) -> None:
    # A message from R (never logged by the node): its receive time, moved by the offset the
    # last recorded ROS reading had from system time.
    sim = _ros_clock_with(99_000_000_000)
    events.begin_replay(1_000_000, [Reading(ClockType.ROS_TIME, 7_000_000, 1_000_000)])
    sim.now()
    events.end()
    events.begin_replay(1_500_000, [])
    fallback = sim.now().nanoseconds
    events.end()
    assert 7_500_000 <= fallback < 7_500_000 + 50_000_000  # plus the replay's own time
    assert events.fallbacks == 1


def test_a_fallback_before_the_last_recorded_reading_does_not_take_the_clock_back(
    events: EventClock,
) -> None:
    # The node applied message k late (recorded reading at 2.0 s, received at 1.0 s); the ring
    # received message k+1, never logged by the node, at 1.5 s: its fallback would be 1.5 s
    # plus the offset, before 2.0 s. It reads 2.0 s: the clock stands, it does not go back.
    sim = _ros_clock_with(99_000_000_000)
    events.begin_replay(1_000_000_000, [Reading(ClockType.ROS_TIME, 2_000_000_000,
                                                2_000_000_000)])
    first = sim.now().nanoseconds
    events.end()
    events.begin_replay(1_500_000_000, [])
    fallback = sim.now().nanoseconds
    events.end()
    assert first == 2_000_000_000
    assert fallback == 2_000_000_000
    assert events.fallbacks == 1


def test_a_fallback_keeps_advancing_so_a_callback_waiting_on_its_clock_gets_there(
    events: EventClock,
) -> None:
    clock = Clock(clock_type=ClockType.SYSTEM_TIME)
    events.begin_replay(time.time_ns() - 10**9, [])
    deadline = clock.now().nanoseconds + 2_000_000  # 2 ms in the event's time
    waited = 0
    while clock.now().nanoseconds < deadline:
        waited += 1
        assert waited < 10**6, 'the fallback clock stood still'
    events.end()


def test_a_reading_of_another_clock_type_than_recorded_is_not_taken_from_the_record(
    events: EventClock,
) -> None:
    system = Clock(clock_type=ClockType.SYSTEM_TIME)
    recorded = Reading(ClockType.ROS_TIME, 5_000_000_000, 1_000)
    events.begin_replay(2_000, [recorded])
    assert system.now().nanoseconds != 5_000_000_000
    events.end()
    assert events.fallbacks == 1


def test_ros_time_without_sim_time_falls_back_to_system_time_exactly(
    events: EventClock,
) -> None:
    events.begin_replay(123_000_000_000, [])
    value = ROSClock().now().nanoseconds
    events.end()
    assert 123_000_000_000 <= value < 123_000_000_000 + 50_000_000


def test_other_threads_read_live_and_are_not_recorded(
    events: EventClock, recorder: _Recorder
) -> None:
    sim = _ros_clock_with(5_000_000_000)
    seen: list[int] = []
    events.begin_replay(1_000, [Reading(ClockType.ROS_TIME, 1, 1_000)])
    thread = threading.Thread(target=lambda: seen.append(sim.now().nanoseconds))
    thread.start()
    thread.join()
    events.end()
    assert seen == [5_000_000_000]
    events.begin_live()
    thread = threading.Thread(target=sim.now)
    thread.start()
    thread.join()
    events.end()
    assert recorder.readings == []


def test_a_clock_polled_in_a_loop_stops_being_recorded_and_says_so_once(
    events: EventClock, recorder: _Recorder
) -> None:
    clock = Clock(clock_type=ClockType.STEADY_TIME)
    events.begin_live()
    for _ in range(MAX_READINGS_PER_EVENT * 3):
        clock.now()
    events.end()
    assert len(recorder.readings) == MAX_READINGS_PER_EVENT
    assert recorder.unrecorded == 1
    events.begin_live()  # the limit is per event
    clock.now()
    events.end()
    assert len(recorder.readings) == MAX_READINGS_PER_EVENT + 1
