"""The ring hands its backlog over before any message that arrives during activation."""

from __future__ import annotations

import threading
from typing import Any, cast

from rory_runtime.log import LogEntry
from rory_runtime.supervisor.ports import Capture
from rory_runtime.supervisor.ring import Ring


def entry(topic: str, n: int) -> LogEntry:
    return LogEntry(topic=topic, msgtype='std_msgs/msg/Int64', recv_ns=n, source_ns=n, seq=n,
                    data=b'')


class _RacingTopic:
    """Delivers a live message from another thread while its backlog is being taken."""

    def __init__(self, topic: str, held: list[LogEntry], live: LogEntry) -> None:
        self.topic = topic
        self.held = held
        self.live = live
        self.thread: threading.Thread | None = None
        self.active = False

    def activate(self, deliver: Any) -> list[LogEntry]:
        self.thread = threading.Thread(target=deliver, args=(self.live,))
        self.thread.start()
        self.thread.join(timeout=0.2)  # give the live message every chance to overtake
        self.active = True
        return list(self.held)


def test_backlog_reaches_the_sink_before_messages_taken_during_activation() -> None:
    ring = Ring(cast(Any, None), 'node')
    a = _RacingTopic('/a', [entry('/a', 1), entry('/a', 3)], entry('/a', 10))
    b = _RacingTopic('/b', [entry('/b', 2)], entry('/b', 11))
    ring.topics = cast(Any, {'/a': a, '/b': b})
    sink = Capture()
    ring.activate(sink)
    for topic in (a, b):
        assert topic.thread is not None
        topic.thread.join(timeout=2.0)
    received = [e.recv_ns for e in sink]
    # backlog of both topics merged in receive order, then the live ones
    assert received[:3] == [1, 2, 3]
    assert sorted(received[3:]) == [10, 11]
