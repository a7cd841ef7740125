"""The supervisor's readers of a node's inputs (rory_runtime/supervisor/readers.py) over a fake
ring: no ManagedNode, no ROS."""

from __future__ import annotations

from fake_supervisor import INPUT, FakeClock, FakeEvents, FakeRing

from rory_runtime.protocol import InputSpec
from rory_runtime.supervisor.ports import Capture, RingPort
from rory_runtime.supervisor.readers import InputReaders
from rory_runtime.supervisor.watchdog import Beat

OTHER = InputSpec(topic='/other', msgtype='std_msgs/msg/String', reliable=True,
                  transient_local=False, depth=10)


class Rings:
    def __init__(self) -> None:
        self.made: list[FakeRing] = []

    def __call__(self, node_id: str) -> RingPort:
        ring = FakeRing()
        self.made.append(ring)
        return ring


def test_a_method_that_logs_makes_its_ring_at_the_first_hello_and_reads_each_input() -> None:
    rings, events = Rings(), FakeEvents(FakeClock())
    readers = InputReaders('n', True, rings, events)
    assert readers.ring is None
    ring = readers.named([INPUT])
    assert rings.made == [ring] and readers.ring is ring and set(rings.made[0].topics) == {'/in'}
    assert readers.named([INPUT]) is ring and len(rings.made) == 1  # the next HELLO: same ring
    readers.added([INPUT, OTHER])
    assert set(rings.made[0].topics) == {'/in', '/other'}
    assert events.of('inputs') == [{'t': 1000.0, 'kind': 'inputs', 'node': 'n',
                                    'added': ['/other']}]


def test_a_method_that_does_not_log_keeps_the_inputs_without_a_ring() -> None:
    rings, events = Rings(), FakeEvents(FakeClock())
    readers = InputReaders('n', False, rings, events)
    assert readers.named([INPUT]) is None and rings.made == [] and readers.specs == [INPUT]
    readers.added([INPUT, OTHER])
    readers.on_beat(Beat(age_s=1.0, late=True))
    assert readers.ring is None and readers.take_early() is None


def test_a_late_beat_keeps_the_inputs_until_the_crash_takes_them_or_a_beat_drops_them() -> None:
    rings = Rings()
    readers = InputReaders('n', True, rings, FakeEvents(FakeClock()))
    readers.named([INPUT])
    (ring,) = rings.made
    readers.on_beat(Beat(age_s=0.7, late=True))
    assert isinstance(ring.sinks[0], Capture) and ring.active_topics == {'/in'}
    readers.on_beat(Beat(age_s=0.0, late=False))  # only slow
    assert ring.active_topics == set() and readers.take_early() is None
    readers.on_beat(Beat(age_s=0.7, late=True))
    taken = readers.take_early()
    assert taken is ring.sinks[1] and ring.active_topics == {'/in'}  # R takes over
    readers.on_beat(Beat(age_s=0.7, late=True))
    readers.stop_early('exited')
    assert ring.active_topics == set() and readers.take_early() is None
