"""Tests of the replay streamer that feeds a recovering node's shadow topic.

The publisher is a fake with ``publish(bytes)``: the streamer calls nothing else.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import pytest
from rclpy.serialization import serialize_message
from std_msgs.msg import Int64

from rory_runtime import protocol
from rory_runtime.errors import LogError
from rory_runtime.log import LogEntry, SegmentStore, read_segment
from rory_runtime.protocol import FLAG_RELAY, Alive, Msg, Release, ReplayPace, unpack
from rory_runtime.supervisor import recovery
from rory_runtime.supervisor.recovery import RecoveryLog, ReplayStreamer, readings_first

NODE = 'integrator'
INT64 = 'std_msgs/msg/Int64'
INCARNATION = 4
BASE_NS = 1_700_000_000_000_000_000
WAIT = 5.0  # generous upper bound for anything that should happen promptly


def int64(value: int) -> bytes:
    return bytes(serialize_message(Int64(data=value)))


def entry(topic: str, n: int, recv_ns: int | None = None) -> LogEntry:
    recv = BASE_NS + n * 1_000_000 if recv_ns is None else recv_ns
    return LogEntry(topic, INT64, recv, BASE_NS - 500 + n, n, int64(n))


class FakePublisher:
    """Records what is published, with the monotonic time of each call."""

    def __init__(self) -> None:
        self.raw: list[bytes] = []
        self.times: list[float] = []
        self._cond = threading.Condition()

    def publish(self, raw: bytes) -> None:
        with self._cond:
            self.raw.append(bytes(raw))
            self.times.append(time.monotonic())
            self._cond.notify_all()

    def wait_for(self, count: int, timeout: float = WAIT) -> None:
        with self._cond:
            assert self._cond.wait_for(lambda: len(self.raw) >= count, timeout), (
                f'{len(self.raw)} of {count} envelopes published'
            )

    @property
    def envelopes(self) -> list[object]:
        with self._cond:
            return [unpack(r) for r in self.raw]


class Released:
    def __init__(self) -> None:
        self.counts: list[int] = []
        self.event = threading.Event()

    def __call__(self, sent: int) -> None:
        self.counts.append(sent)
        self.event.set()


def ended(thread: threading.Thread, timeout: float = WAIT) -> bool:
    """Whether the thread has finished within timeout.

    Deliberately not ``join``/``is_alive``: see test_streamer_can_be_joined_like_any_thread.
    """
    deadline = time.monotonic() + timeout
    while thread in threading.enumerate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.002)
    return True


def as_msg(envelope: object, e: LogEntry, flags: int = 0) -> bool:
    return envelope == Msg(INCARNATION, flags, e.recv_ns, e.source_ns, e.seq, e.topic, e.data)


@pytest.fixture(autouse=True)
def no_keepalive(monkeypatch: pytest.MonkeyPatch) -> None:
    """An idle relay says it is alive (ALIVE) every RELAY_KEEPALIVE_S; the tests that are not
    about that would see one on a slow machine, so it is an hour unless a test says so."""
    monkeypatch.setattr(recovery, 'RELAY_KEEPALIVE_S', 3600.0)


@pytest.fixture
def segments(tmp_path: Path) -> SegmentStore:
    return SegmentStore(tmp_path / 'store', NODE)


@pytest.fixture
def streamers() -> Iterator[list[ReplayStreamer]]:
    started: list[ReplayStreamer] = []
    yield started
    for s in started:
        s.stop()
    for s in started:
        assert ended(s)


def seqs(envelopes: Sequence[object]) -> list[int]:
    """The sequence numbers of MSG envelopes (and fails on any other kind)."""
    assert all(isinstance(e, Msg) for e in envelopes), envelopes
    return [e.seq for e in envelopes if isinstance(e, Msg)]


Make = Callable[..., tuple['ReplayStreamer', 'FakePublisher', RecoveryLog, 'Released']]
"""The ``make`` fixture: a streamer, its publisher, R and its release."""


@pytest.fixture
def make(
    segments: SegmentStore, streamers: list[ReplayStreamer]
) -> Callable[..., tuple[ReplayStreamer, FakePublisher, RecoveryLog, Released]]:
    def factory(
        backlog: list[LogEntry] | Iterator[LogEntry],
        r_entries: list[LogEntry],
        pace: ReplayPace = ReplayPace.FAST,
        crashed_ns: int = BASE_NS + 10**12,
        rlog: RecoveryLog | None = None,
    ) -> tuple[ReplayStreamer, FakePublisher, RecoveryLog, Released]:
        if rlog is None:
            rlog = RecoveryLog(segments, {})
        rlog.add_backlog(r_entries)
        pub = FakePublisher()
        released = Released()
        streamer = ReplayStreamer(
            pub,
            INCARNATION,
            iter(backlog),
            rlog,
            pace,
            crashed_ns,
            released,
        )
        streamers.append(streamer)
        return streamer, pub, rlog, released

    return factory


# --------------------------------------------------------------------------- FAST


def test_fast_streams_backlog_then_r_then_one_release(make: Make) -> None:
    backlog = [entry('/a', 1), entry('/b', 2), entry('/a', 3)]
    r_entries = [entry('/a', 4), entry('/b', 5)]
    streamer, pub, rlog, released = make(backlog, r_entries)
    streamer.start()
    assert released.event.wait(WAIT)
    envelopes = pub.envelopes
    assert len(envelopes) == 6
    for envelope, e in zip(envelopes[:5], backlog + r_entries, strict=True):
        assert as_msg(envelope, e)
    assert envelopes[5] == Release(INCARNATION, rlog.number + 1, 5)
    assert released.counts == [5]
    assert streamer.sent == 5


def test_release_delivered_equals_msg_envelopes_sent(make: Make) -> None:
    backlog = [entry('/a', n) for n in range(7)]
    streamer, pub, rlog, released = make(backlog, [entry('/b', 100), entry('/b', 101)])
    streamer.start()
    assert released.event.wait(WAIT)
    envelopes = pub.envelopes
    releases = [e for e in envelopes if isinstance(e, Release)]
    msgs = [e for e in envelopes if isinstance(e, Msg)]
    assert len(releases) == 1
    assert releases[0].delivered == len(msgs) == 9
    assert releases[0].next_segment == rlog.number + 1


def test_release_with_nothing_to_replay(make: Make) -> None:
    streamer, pub, rlog, released = make([], [])
    streamer.start()
    assert released.event.wait(WAIT)
    assert pub.envelopes == [Release(INCARNATION, rlog.number + 1, 0)]
    assert released.counts == [0]


def test_release_seals_r(make: Make, segments: SegmentStore) -> None:
    r_entries = [entry('/a', 1)]
    streamer, _pub, rlog, released = make([], r_entries)
    assert not rlog.sealed
    streamer.start()
    assert released.event.wait(WAIT)
    assert rlog.sealed
    path = segments.path(rlog.number)
    assert (path / 'metadata.yaml').is_file()
    assert list(read_segment(path)) == r_entries


def test_r_sealed_before_release_is_published(
    make: Make, monkeypatch: pytest.MonkeyPatch
) -> None:
    streamer, pub, rlog, _released = make([], [entry('/a', 1)])
    sealed_at_release: list[bool] = []
    original = pub.publish

    def publish(raw: bytes) -> None:
        if isinstance(unpack(raw), Release):
            sealed_at_release.append(rlog.sealed)
        original(raw)

    monkeypatch.setattr(pub, 'publish', publish)
    streamer.start()
    pub.wait_for(2)
    assert sealed_at_release == [True]


def test_entries_added_to_r_during_the_backlog_come_before_release(
    make: Make, segments: SegmentStore
) -> None:
    rlog = RecoveryLog(segments, {})
    during = entry('/live', 50)

    def backlog() -> Iterator[LogEntry]:
        yield entry('/a', 1)
        rlog.add(during)  # arrives through the ring while the backlog streams
        yield entry('/a', 2)

    streamer, pub, _rlog, released = make(backlog(), [entry('/live', 40)], rlog=rlog)
    streamer.start()
    assert released.event.wait(WAIT)
    envelopes = pub.envelopes
    assert seqs(envelopes[:-1]) == [1, 2, 40, 50]
    assert all(isinstance(e, Msg) and e.flags == 0 for e in envelopes[:-1])
    assert envelopes[-1] == Release(INCARNATION, rlog.number + 1, 4)
    assert list(rlog.relay) == []


def test_after_release_entries_are_relayed_with_flag(make: Make) -> None:
    streamer, pub, rlog, released = make([entry('/a', 1)], [entry('/a', 2)])
    streamer.start()
    assert released.event.wait(WAIT)
    late = [entry('/a', 10), entry('/b', 11), entry('/a', 12)]
    for e in late:
        rlog.add(e)
    pub.wait_for(3 + 3)
    tail = pub.envelopes[3:]
    for envelope, e in zip(tail, late, strict=True):
        assert as_msg(envelope, e, FLAG_RELAY)
    assert streamer.sent == 2 + 3
    assert rlog.entries == [entry('/a', 2)]  # relayed entries are not part of R's segment


def test_switched_topics_are_not_relayed(make: Make) -> None:
    streamer, pub, rlog, released = make([], [entry('/a', 1)])
    streamer.start()
    assert released.event.wait(WAIT)
    streamer.switched.add('/b')
    for e in [entry('/b', 10), entry('/a', 11), entry('/b', 12), entry('/a', 13)]:
        rlog.add(e)
    pub.wait_for(2 + 2)
    # The relay is FIFO: once /a 13 is out, both /b entries have been consumed.
    time.sleep(0.05)
    envelopes = pub.envelopes
    assert len(envelopes) == 4
    assert as_msg(envelopes[2], entry('/a', 11), FLAG_RELAY)
    assert as_msg(envelopes[3], entry('/a', 13), FLAG_RELAY)
    assert not any(isinstance(e, Msg) and e.topic == '/b' for e in envelopes)
    assert len(rlog.relay) == 0  # switched entries are consumed, not kept


def test_an_idle_relay_says_it_is_alive(
    make: Make, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Nothing reaches the ring (a link outage): the node must not take the relay for dead.
    monkeypatch.setattr(recovery, 'RELAY_KEEPALIVE_S', 0.05)
    streamer, pub, _rlog, released = make([], [entry('/a', 1)])
    streamer.start()
    assert released.event.wait(WAIT)
    pub.wait_for(2 + 3)
    assert pub.envelopes[2:5] == [Alive(INCARNATION)] * 3
    assert streamer.sent == 1  # ALIVEs are no messages: RELEASE's count is unchanged


def test_an_alive_follows_only_a_keepalive_period_without_anything_sent(
    make: Make, monkeypatch: pytest.MonkeyPatch
) -> None:
    period = 0.2
    monkeypatch.setattr(recovery, 'RELAY_KEEPALIVE_S', period)
    streamer, pub, rlog, released = make([], [entry('/a', 1)])
    streamer.start()
    assert released.event.wait(WAIT)
    rlog.add(entry('/a', 2))
    # The relayed message, then an ALIVE (on a slow machine another may come before it).
    deadline = time.monotonic() + WAIT
    while True:
        envelopes, times = pub.envelopes, list(pub.times)
        relayed = [i for i, e in enumerate(envelopes) if i >= 2 and isinstance(e, Msg)]
        if relayed and len(envelopes) > relayed[0] + 1:
            break
        assert time.monotonic() < deadline, envelopes
        time.sleep(0.01)
    relayed_at = relayed[0]
    assert envelopes[relayed_at + 1] == Alive(INCARNATION)
    # Never sooner than a period after the message: the relay was not idle.
    assert times[relayed_at + 1] - times[relayed_at] >= period - 0.01


def test_stop_ends_the_relay_promptly(make: Make) -> None:
    streamer, pub, _rlog, released = make([], [entry('/a', 1)])
    streamer.start()
    assert released.event.wait(WAIT)
    time.sleep(0.05)  # let the relay block waiting for entries
    t0 = time.monotonic()
    streamer.stop()
    assert ended(streamer)
    elapsed = time.monotonic() - t0
    assert elapsed < 0.45  # woken by stop(), not by its 0.5 s poll
    assert len(pub.raw) == 2


def test_streamer_can_be_joined_like_any_thread(make: Make) -> None:
    """ReplayStreamer is a threading.Thread: join() and is_alive() must work after stop()."""
    streamer, _pub, _rlog, released = make([], [])
    streamer.start()
    assert released.event.wait(WAIT)
    assert streamer.is_alive()  # relaying
    streamer.stop()
    streamer.join(WAIT)
    assert not streamer.is_alive()


def test_stop_during_paced_backlog_sends_no_release(make: Make) -> None:
    crashed = BASE_NS + 100 * 10**9
    backlog = [entry('/a', 1, BASE_NS), entry('/a', 2, BASE_NS + 30 * 10**9)]
    streamer, pub, rlog, released = make(backlog, [], ReplayPace.PACED, crashed)
    streamer.start()
    pub.wait_for(1)
    t0 = time.monotonic()
    streamer.stop()
    assert ended(streamer)
    assert time.monotonic() - t0 < 1.0
    assert not released.event.is_set()
    assert all(not isinstance(e, Release) for e in pub.envelopes)
    assert not rlog.sealed


def test_log_error_while_reading_the_backlog_is_recorded(make: Make) -> None:
    def backlog() -> Iterator[LogEntry]:
        yield entry('/a', 1)
        raise LogError(Path('/x/0000000001'), 'malformed message record at offset 8')

    streamer, pub, rlog, released = make(backlog(), [entry('/a', 2)])
    streamer.start()
    assert ended(streamer)
    assert streamer.error is not None
    assert 'malformed message record' in streamer.error
    assert not released.event.is_set()
    assert len(pub.envelopes) == 1
    assert not any(isinstance(e, Release) for e in pub.envelopes)
    assert not rlog.sealed
    rlog.close()


def test_fast_ignores_recorded_gaps(make: Make) -> None:
    backlog = [entry('/a', n, BASE_NS + n * 10**9) for n in range(3)]  # 1 s apart
    streamer, _pub, _rlog, released = make(
        backlog, [], ReplayPace.FAST, crashed_ns=BASE_NS + 10 * 10**9
    )
    t0 = time.monotonic()
    streamer.start()
    assert released.event.wait(WAIT)
    assert time.monotonic() - t0 < 1.0


# --------------------------------------------------------------------------- PACED


def test_paced_spaces_entries_before_the_crash_by_recorded_gaps(
    make: Make,
) -> None:
    gap = 100_000_000  # 100 ms
    crashed = BASE_NS + 10 * gap
    backlog = [entry('/a', n, BASE_NS + n * gap) for n in range(3)]
    streamer, pub, _rlog, released = make(backlog, [], ReplayPace.PACED, crashed)
    streamer.start()
    assert released.event.wait(WAIT)
    t = pub.times
    assert seqs(pub.envelopes[:3]) == [0, 1, 2]
    assert t[0] <= t[1] <= t[2]
    assert t[1] - t[0] >= 0.08
    assert t[2] - t[0] >= 0.18


def test_paced_does_not_pace_entries_after_the_crash(make: Make) -> None:
    gap = 100_000_000
    crashed = BASE_NS + 2 * gap
    backlog = [entry('/a', 0, BASE_NS), entry('/a', 1, BASE_NS + gap), entry('/a', 2, crashed)]
    after = [entry('/a', 3, crashed + 5 * 10**9), entry('/a', 4, crashed + 10 * 10**9)]
    streamer, pub, rlog, released = make(backlog, after, ReplayPace.PACED, crashed)
    streamer.start()
    assert released.event.wait(WAIT)
    t = pub.times
    envelopes = pub.envelopes
    assert seqs(envelopes[:5]) == [0, 1, 2, 3, 4]
    assert envelopes[5] == Release(INCARNATION, rlog.number + 1, 5)
    assert t[2] - t[0] >= 0.18  # the entry received exactly at the crash is still paced
    assert t[5] - t[2] < 1.0  # 5 s and 10 s recorded gaps after the crash are not waited for


def test_paced_r_entries_before_the_crash_are_paced_after_the_backlog(
    make: Make,
) -> None:
    """The ring's backlog in R was received before the crash: it keeps its recorded gap."""
    gap = 100_000_000
    crashed = BASE_NS + 10 * gap
    backlog = [entry('/a', 0, BASE_NS)]
    ring_backlog = [entry('/b', 1, BASE_NS + 2 * gap)]
    streamer, pub, _rlog, released = make(backlog, ring_backlog, ReplayPace.PACED, crashed)
    streamer.start()
    assert released.event.wait(WAIT)
    assert pub.times[1] - pub.times[0] >= 0.18


def test_an_events_clock_readings_are_sent_just_before_it() -> None:
    def record(topic: str, n: int) -> LogEntry:
        return LogEntry(topic, 'builtin_interfaces/msg/Time', n, n, n, b'')

    log = [entry('/a', 1), record(protocol.CLOCK_RECORD, 2), record(protocol.CLOCK_RECORD, 3),
           record(protocol.TIMER_RECORD, 4), record(protocol.CLOCK_RECORD, 5), entry('/a', 6),
           entry('/a', 7), record(protocol.CLOCK_RECORD, 8)]
    assert [e.seq for e in readings_first(log)] == [2, 3, 1, 5, 4, 6, 8, 7]
    assert list(readings_first([])) == []


def test_a_failure_reading_the_log_still_sends_the_event_read_before_it() -> None:
    def log() -> Iterator[LogEntry]:
        yield entry('/a', 1)
        raise LogError(Path('/x/0000000001'), 'torn')

    sent: list[LogEntry] = []
    with pytest.raises(LogError):
        sent.extend(readings_first(log()))
    assert [e.topic for e in sent] == ['/a']
