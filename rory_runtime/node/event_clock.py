"""The node's clocks inside its callbacks: each reading recorded while live, read back in replay.

A callback that computes with time (``dt`` from ``self.get_clock().now()``) is a function of
the times it reads as much as of its message. So, inside an *event* (a message applied or a
timer tick, under the runtime's lock, on the executor's thread), every call of
``rclpy.clock.Clock.now`` - ``Node.get_clock()``, ``ROSClock``, and any ``Clock`` the node
made, of any clock type - goes through :class:`EventClock`:

* live, the reading is taken as usual and written to the node's log (a clock record,
  :data:`~rory_runtime.protocol.CLOCK_RECORD`) before it is returned: write-ahead, like a
  message;
* in replay, the event's recorded readings are returned in order, so the callback computes
  exactly what it computed before the crash.

A replayed event with no recorded reading left (a message from the recovery log R, which the
node never logged; the callback that was running when the node died) reads the event's
recorded system time, moved by the offset the last recorded reading of that clock type had
from system time, plus the time the replay of this event has taken so far (so a callback that
waits for its clock to pass a deadline still gets there). Outside events (``__init__``, other
threads, RORY's own code) clocks read live time.

``time.time()`` and friends are not rclpy clocks and cannot be intercepted:
``rory-instrument`` warns where a node reads them (docs/keyvars.md).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from typing import NamedTuple

from rclpy.clock import Clock, ROSClock
from rclpy.clock_type import ClockType
from rclpy.time import Time

# More readings than this in one event stop being recorded (a callback polling its clock in
# a loop would otherwise fill the log); the rest are live, and replay them from the fallback.
MAX_READINGS_PER_EVENT = 64


class Reading(NamedTuple):
    """One recorded clock reading."""

    clock_type: int  # rclpy's ClockType value
    value_ns: int  # what the clock returned
    at_ns: int  # system time when it was read


# Writes one reading to the node's log; raises nothing (the runtime reports its own errors).
Recorder = Callable[[Reading], None]

original_now = Clock.now
_installed = False


class Current:
    """The event running now, if any (one per process: events run under the runtime's lock).

    A holder rather than a module global so that the applier's hot path (applier.py) can start
    and end a live event with attribute stores instead of calls to :meth:`EventClock.begin_live`
    and :meth:`EventClock.end`: a message then touches two Python functions fewer.
    """

    __slots__ = ('event',)

    def __init__(self) -> None:
        self.event: EventClock | None = None


current = Current()


def _now(clock: Clock) -> Time:
    event = current.event
    if event is None or event.thread != threading.get_ident():
        return original_now(clock)
    return event.read(clock)


def install() -> None:
    """Route ``Clock.now`` through the active event, if any (idempotent, process-wide)."""
    global _installed
    if not _installed:
        Clock.now = _now  # type: ignore[method-assign,assignment]
        _installed = True


def active() -> EventClock | None:
    """The event running on this thread, if any."""
    event = current.event
    return event if event is not None and event.thread == threading.get_ident() else None


def in_event() -> bool:
    """Whether this thread is running an event of the node (a callback RORY applies)."""
    event = current.event
    return event is not None and event.thread == threading.get_ident()


def _live_offset(clock: Clock, clock_type: int) -> int:
    """How far ``clock`` reads from system time right now."""
    if clock_type == ClockType.SYSTEM_TIME:
        return 0
    if clock_type == ClockType.ROS_TIME and isinstance(clock, ROSClock) \
            and not clock.ros_time_is_active:
        return 0  # ROS time without a /clock is system time
    return int(original_now(clock).nanoseconds) - time.time_ns()


class EventClock:
    """The clock readings of one node's events: recorded live, returned in replay.

    Args:
        record: Writes a live reading to the node's log before it is returned.
        on_unrecorded: Called once per event whose readings stop being recorded (more than
            :data:`MAX_READINGS_PER_EVENT`).
    """

    def __init__(self, record: Recorder, on_unrecorded: Callable[[], None]) -> None:
        self._record = record
        self._on_unrecorded = on_unrecorded
        # What begin_live sets (the applier's hot path sets them itself, the same way): the
        # event's thread, live or replayed, and the readings it took so far.
        self.thread = 0
        self.replaying = False
        self.count = 0
        self._readings: deque[Reading] = deque()
        self._event_ns = 0
        self._began = 0.0
        # Per clock type, the last recorded reading's distance from system time.
        self._offsets: dict[int, int] = {}
        # Per clock type, the latest reading a replayed event returned: a fallback never goes
        # below it (a node computing dt must not see its clock go back).
        self._latest: dict[int, int] = {}
        self.fallbacks = 0  # replayed readings that had no recorded value

    def begin_live(self) -> None:
        """A live event starts on this thread: record its readings."""
        self.thread = threading.get_ident()
        self.replaying = False
        self.count = 0
        current.event = self

    def begin_replay(self, event_ns: int, readings: Iterable[Reading]) -> None:
        """A replayed event starts: return ``readings`` in order.

        Args:
            event_ns: The event's recorded system time (a message's receive time, a tick's
                time), the base of readings with no recorded value.
            readings: What the event read when it ran live, in order.
        """
        self.thread = threading.get_ident()
        self.replaying = True
        self._readings = deque(readings)
        self._event_ns = event_ns
        self._began = time.monotonic()
        current.event = self

    def end(self) -> None:
        """The event is over: clocks read live time again."""
        current.event = None
        self._readings.clear()

    def read(self, clock: Clock) -> Time:
        """What ``clock.now()`` returns inside the event."""
        clock_type = int(clock.clock_type)
        if self.replaying:
            return Time(nanoseconds=self._replayed(clock, clock_type),
                        clock_type=clock.clock_type)
        now = original_now(clock)
        self.count += 1
        if self.count <= MAX_READINGS_PER_EVENT:
            self._record(Reading(clock_type, int(now.nanoseconds), time.time_ns()))
        elif self.count == MAX_READINGS_PER_EVENT + 1:
            self._on_unrecorded()
        return now

    def event_time(self, clock: Clock) -> int | None:
        """When a replayed event happened on ``clock`` (its recorded system time, moved by the
        offset that clock's last recorded reading had), without taking one of its readings;
        None in a live event, whose clocks read live time."""
        if not self.replaying:
            return None
        clock_type = int(clock.clock_type)
        offset = self._offsets.get(clock_type)
        if offset is None:
            offset = _live_offset(clock, clock_type)
        return max(0, self._event_ns + offset)

    def _replayed(self, clock: Clock, clock_type: int) -> int:
        readings = self._readings
        latest = self._latest.get(clock_type, 0)
        if readings and readings[0].clock_type == clock_type:
            reading = readings.popleft()
            self._offsets[clock_type] = reading.value_ns - reading.at_ns
            self._latest[clock_type] = max(latest, reading.value_ns)
            return reading.value_ns
        self.fallbacks += 1
        offset = self._offsets.get(clock_type)
        if offset is None:
            offset = _live_offset(clock, clock_type)
        elapsed = int((time.monotonic() - self._began) * 1e9)
        # The event's own time can lie before the last reading returned: a message the ring
        # received before the node applied the one logged before it (a node running late on a
        # loaded computer). Its clock does not go back for that: it reads the last reading.
        value = max(0, self._event_ns + offset + elapsed, latest)
        self._latest[clock_type] = value
        return value
