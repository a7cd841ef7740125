"""A message the node dies applying twice in a row is quarantined with its bytes."""

from __future__ import annotations

import base64
import json
from pathlib import Path

from fake_supervisor import Harness
from rclpy.serialization import serialize_message
from std_msgs.msg import Int64

from rory_runtime.inflight import InFlightSlot, slot_path
from rory_runtime.log import LogEntry, SegmentStore
from rory_runtime.supervisor.poison import PoisonGuard


def _entry(n: int) -> LogEntry:
    return LogEntry('/numbers', 'std_msgs/msg/Int64', 1000 + n, n, n,
                    bytes(serialize_message(Int64(data=n))))


def test_same_message_twice_is_quarantined_and_remembered(tmp_path: Path) -> None:
    segments = SegmentStore(tmp_path, 'n')
    writer = segments.open(1)
    for n in (1, 2, 3):
        e = _entry(n)
        writer.write(e.topic, e.msgtype, e.recv_ns, e.source_ns, e.seq, e.data)
    writer.close()
    guard = PoisonGuard(tmp_path, 'n', segments)
    slot = InFlightSlot(slot_path(tmp_path, 'n'), incarnation=1)
    slot.busy('/numbers', (3, 3), 1003)
    assert guard.on_crash(1) is None  # a suspect, not yet poison
    slot.close()
    slot = InFlightSlot(slot_path(tmp_path, 'n'), incarnation=2)
    slot.busy('/numbers', (3, 3), 1003)
    quarantined = guard.on_crash(2)
    assert quarantined is not None and quarantined.ident == (3, 3)
    record = json.loads(quarantined.path.read_text())
    assert record['topic'] == '/numbers' and record['type'] == 'std_msgs/msg/Int64'
    assert base64.b64decode(record['cdr_base64']) == _entry(3).data
    assert json.loads(guard.env_value()) == [['/numbers', 3, 3]]
    # a new supervisor reads the quarantine back
    assert PoisonGuard(tmp_path, 'n', segments).keys == {('/numbers', (3, 3))}


def test_different_messages_or_no_message_are_not_poison(tmp_path: Path) -> None:
    segments = SegmentStore(tmp_path, 'n')
    guard = PoisonGuard(tmp_path, 'n', segments)
    slot = InFlightSlot(slot_path(tmp_path, 'n'), incarnation=1)
    slot.busy('/numbers', (3, 3), 1003)
    assert guard.on_crash(1) is None
    slot = InFlightSlot(slot_path(tmp_path, 'n'), incarnation=2)
    slot.busy('/numbers', (4, 4), 1004)
    assert guard.on_crash(2) is None  # died elsewhere: a new suspect
    slot = InFlightSlot(slot_path(tmp_path, 'n'), incarnation=3)
    slot.idle()
    assert guard.on_crash(3) is None  # died between messages
    slot.busy('/numbers', (4, 4), 1004)
    assert guard.on_crash(2) is None  # the slot belongs to another process
    assert guard.keys == set()


def _dies_applying(h: Harness, ident: tuple[int, int] | None) -> None:
    """The node's current process dies applying /numbers ``ident`` (None: between messages)."""
    slot = InFlightSlot(h.node.slot, incarnation=h.node.incarnation)
    if ident is not None:
        slot.busy('/numbers', ident, 1000 + ident[1])
    slot.close()
    h.exit(1)


def test_the_recovered_event_names_what_its_crashes_died_on_and_what_was_quarantined(
    tmp_path: Path
) -> None:
    h = Harness(tmp_path)
    h.node.start()
    h.up()
    _dies_applying(h, (77, 7))  # live
    _dies_applying(h, (77, 7))  # again, replaying it: poison
    h.tick(0.5)  # the second crash in a row waits the backoff
    h.up()  # the third process skips it
    (quarantined,) = h.sup.events_log.of('quarantined')
    (recovered,) = h.sup.events_log.of('recovered')
    assert recovered['crashes'] == 2
    assert recovered['died_on'] == [
        {'incarnation': 1, 'topic': '/numbers', 'source_ns': 77, 'seq': 7},
        {'incarnation': 2, 'topic': '/numbers', 'source_ns': 77, 'seq': 7},
    ]
    assert recovered['quarantined'] == [
        {'topic': '/numbers', 'source_ns': 77, 'seq': 7, 'path': quarantined['path']}]
    # The next recovery names only its own crash: one killed between two messages.
    h.tick(11.0)  # ran stable: no backoff
    _dies_applying(h, None)
    h.up()
    second = h.sup.events_log.of('recovered')[-1]
    assert (second['died_on'], second['quarantined']) == ([], [])
