"""The applier (node/applier.py): a message written ahead to the log, the in-flight slot busy while
its callback runs, duplicates and quarantined messages skipped, windows and counters moved, the
event's clock readings recorded; the live path and the general one doing the same.

Driven with stand-ins: a subscription (runtime_fakes.py), a log that records what is written;
the in-flight slot and, where said, the log segments are the real ones.
"""

from __future__ import annotations

import sys
import threading
from pathlib import Path
from types import FrameType
from typing import Any

import pytest
from rclpy.clock import ROSClock
from rclpy.qos import QoSProfile
from runtime_fakes import FakeSubscription, cdr, info
from std_msgs.msg import Int64

from rory_runtime import protocol
from rory_runtime.inflight import InFlightSlot, read_slot, slot_path
from rory_runtime.log import SegmentStore, SegmentWriter
from rory_runtime.node import event_clock
from rory_runtime.node.applier import STAT_NAMES, Applier, Window
from rory_runtime.node.routing import Input, TopicPhase
from rory_runtime.protocol import InputSpec, MessageId

TOPIC = '/numbers'


class _Writer:
    """A segment that records what is written to it, in order, into ``log``."""

    def __init__(self, log: list[tuple[Any, ...]]) -> None:
        self.log = log

    def write(self, topic: str, msgtype: str, recv_ns: int, source_ns: int, seq: int,
              data: bytes, offered_qos: Any = None) -> None:
        self.log.append((topic, recv_ns, source_ns, seq))


class _Segments:
    """The checkpointer's side of the log: the segment being written, opened on first use."""

    def __init__(self) -> None:
        self.log: list[tuple[Any, ...]] = []
        self.writer: SegmentWriter | None = None

    def segment(self) -> SegmentWriter:
        if self.writer is None:
            self.writer = _Writer(self.log)  # type: ignore[assignment]
        assert self.writer is not None
        return self.writer


class _Node:
    """The user's callback on /numbers: what it saw while it ran."""

    def __init__(self, slot: Path, segments: _Segments) -> None:
        self.slot = slot
        self.segments = segments
        self.seen: list[tuple[int, Any, int]] = []  # number, slot, records logged before it
        self.raise_on: int | None = None
        self.read_clock = False

    def on_number(self, msg: Int64) -> None:
        self.seen.append((msg.data, read_slot(self.slot), len(self.segments.log)))
        if self.read_clock:
            ROSClock().now()
        if msg.data == self.raise_on:
            raise RuntimeError('the callback failed')


def _input(callback: Any) -> Input:
    sub = FakeSubscription(TOPIC, callback)
    spec = InputSpec.from_qos(TOPIC, 'std_msgs/msg/Int64', QoSProfile(depth=10))
    return Input(sub=sub, topic=TOPIC, msg_type=Int64, type_name='std_msgs/msg/Int64',  # type: ignore[arg-type]
                 callback=callback, with_info=False, user_raw=False, spec=spec,
                 phase=TopicPhase.LIVE)


def _applier(tmp_path: Path, *, logs: bool = True,
             quarantined: frozenset[tuple[str, MessageId]] = frozenset(),
             ) -> tuple[Applier, _Node, Input, list[str]]:
    segments = _Segments()
    slot = slot_path(tmp_path, 'n')
    errors: list[str] = []
    applier = Applier(lock=threading.RLock(), logs=logs, quarantined=quarantined,
                      inflight=InFlightSlot(slot, 1), segments=segments, error=errors.append)
    node = _Node(slot, segments)
    inp = _input(node.on_number)
    applier.windows[TOPIC] = Window(protocol.window_size(inp.spec))
    return applier, node, inp, errors


def test_a_live_message_is_logged_then_applied_with_the_slot_busy_then_counted(
    tmp_path: Path,
) -> None:
    applier, node, inp, errors = _applier(tmp_path)
    live = applier.live_path(inp)
    live(cdr(1), info(1))
    [(number, busy, logged_before)] = node.seen
    assert number == 1 and logged_before == 1  # written ahead
    assert busy is not None and busy.topic == TOPIC and busy.ident == (1, 1)
    assert busy.recv_ns == 1_001
    assert read_slot(slot_path(tmp_path, 'n')) is None  # idle again
    assert (1, 1) in applier.windows[TOPIC]
    assert applier.stats['applied'] == 1 and applier.progress == 1 and errors == []


def test_a_duplicate_or_a_quarantined_message_is_skipped_and_counted(tmp_path: Path) -> None:
    applier, node, inp, _ = _applier(tmp_path, quarantined=frozenset({(TOPIC, (2, 2))}))
    live = applier.live_path(inp)
    for n in (1, 1, 2, 3):
        live(cdr(n), info(n))
    assert [n for n, _, _ in node.seen] == [1, 3]
    assert applier.stats['duplicates'] == 1 and applier.stats['quarantined'] == 1
    assert applier.stats['applied'] == 2


def test_a_callback_that_raises_is_remembered_and_leaves_no_event_open(tmp_path: Path) -> None:
    applier, node, inp, _ = _applier(tmp_path)
    node.raise_on = 1
    with pytest.raises(RuntimeError, match='the callback failed'):
        applier.live_path(inp)(cdr(1), info(1))
    assert applier.callback_failed
    assert event_clock.current.event is None
    assert read_slot(slot_path(tmp_path, 'n')) is not None  # the message it died on


def test_clock_readings_inside_a_live_message_are_logged_after_it(tmp_path: Path) -> None:
    applier, node, inp, _ = _applier(tmp_path)
    node.read_clock = True
    applier.live_path(inp)(cdr(1), info(1))
    segments = node.segments
    assert [record[0] for record in segments.log] == [TOPIC, protocol.CLOCK_RECORD]
    ROSClock().now()  # outside the event: not logged
    assert len(segments.log) == 2


def test_without_a_log_nothing_is_written_and_clocks_are_left_alone(tmp_path: Path) -> None:
    applier, node, inp, _ = _applier(tmp_path, logs=False)
    node.read_clock = True
    applier.live_path(inp)(cdr(1), info(1))
    segments = node.segments
    assert segments.log == [] and applier.clock is None
    assert [n for n, _, _ in node.seen] == [1] and applier.stats['applied'] == 1


def test_the_live_path_does_what_apply_does(tmp_path: Path) -> None:
    # live_path is apply(log=True) written out in one function: the same log, slot, window,
    # counters.
    results = []
    for way in ('live_path', 'apply'):
        applier, node, inp, _ = _applier(tmp_path / way)
        node.read_clock = True
        live = applier.live_path(inp)
        for n in (1, 2, 3):
            if way == 'live_path':
                live(cdr(n), info(n))
            else:
                applier.apply(inp, cdr(n), info(n), (n, n), log=True)
        segments = node.segments
        # (a clock record by its clock type: its times are the moment's)
        logged = [(r[0], r[3]) if r[0] == protocol.CLOCK_RECORD else r for r in segments.log]
        results.append((node.seen, logged, applier.windows[TOPIC].snapshot(), applier.stats,
                        applier.progress))
    assert results[0] == results[1]


def test_the_counters_are_what_the_released_status_carries() -> None:
    stats = dict.fromkeys(STAT_NAMES, 0)
    assert protocol.ReleasedStatus(**stats).to_json() == stats


class _RealSegments:
    def __init__(self, store: SegmentStore) -> None:
        self.store = store
        self.writer: SegmentWriter | None = None

    def segment(self) -> SegmentWriter:
        if self.writer is None:
            self.writer = self.store.open(1)
        return self.writer


@pytest.mark.parametrize('logs', [False, True])
def test_a_live_message_runs_through_one_function_of_the_runtime_and_the_log_writer(
    tmp_path: Path, logs: bool,
) -> None:
    # What a message costs the node's process grows with the distinct Python functions it runs
    # through (issue 36): the live path is one function, and calls nothing of RORY's but the
    # segment writer's write.
    segments = _RealSegments(SegmentStore(tmp_path, 'n'))
    applier = Applier(lock=threading.RLock(), logs=logs, quarantined=frozenset(),
                      inflight=InFlightSlot(slot_path(tmp_path, 'n'), 1), segments=segments,
                      error=lambda message: None)
    inp = _input(lambda msg: None)
    applier.windows[TOPIC] = Window(protocol.window_size(inp.spec))
    live = applier.live_path(inp)
    live(cdr(1), info(1))  # (the segment opens at the first message)
    touched: set[str] = set()

    def profile(frame: FrameType, event: str, _arg: Any) -> None:
        if event == 'call' and '/rory_runtime/' in frame.f_code.co_filename:
            touched.add(f'{Path(frame.f_code.co_filename).stem}.{frame.f_code.co_name}')

    raw, message_info = cdr(2), info(2)
    sys.setprofile(profile)
    try:
        live(raw, message_info)
    finally:
        sys.setprofile(None)
    if segments.writer is not None:
        segments.writer.close()
    writer = {'log.write', 'log.write_message'} if logs else set()
    assert touched == {'applier.live'} | writer
