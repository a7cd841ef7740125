"""The ring with real rclpy readers: what it hands over, and what it says when DDS drops."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import QoSProfile
from std_msgs.msg import Int64

from rory_runtime.log import LogEntry, SegmentStore
from rory_runtime.protocol import InputSpec, ring_depth
from rory_runtime.supervisor.ports import Capture
from rory_runtime.supervisor.recovery import RecoveryLog
from rory_runtime.supervisor.ring import Ring, RingContext

pytestmark = pytest.mark.ros

SPEC = InputSpec('/burst', 'std_msgs/msg/Int64', True, False, 10)


@pytest.fixture
def ring(ros_domain: int) -> Iterator[Ring]:
    ctx = RingContext(domain_id=ros_domain)
    ring = Ring(ctx, 'node')
    ring.ensure([SPEC])
    try:
        yield ring
    finally:
        for topic in ring.topics.values():
            topic.destroy()
        ctx.shutdown()


@pytest.fixture
def publisher(ros_domain: int, ring: Ring) -> Iterator[Publisher]:
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    node = Node('burst_publisher', context=ctx)
    pub = node.create_publisher(Int64, SPEC.topic, QoSProfile(depth=1000))
    deadline = time.monotonic() + 10.0
    while ring.publisher_count(SPEC.topic) < 1 or pub.get_subscription_count() < 1:
        assert time.monotonic() < deadline, 'ring reader and publisher never matched'
        time.sleep(0.01)
    try:
        yield pub
    finally:
        node.destroy_node()
        ctx.try_shutdown()


def _settle(pub: Publisher, taken: list[LogEntry], last: int) -> None:
    pub.wait_for_all_acked(Duration(seconds=5.0))
    deadline = time.monotonic() + 5.0
    while (not taken or taken[-1].seq != last) and time.monotonic() < deadline:
        time.sleep(0.01)


def test_passive_history_then_live_messages_in_order(ring: Ring, publisher: Publisher) -> None:
    # Passive, DDS keeps the last ring_depth messages; activation hands them over, then each
    # new one as it comes.
    depth = ring_depth(SPEC)
    for n in range(1, depth + 11):
        publisher.publish(Int64(data=n))
    publisher.wait_for_all_acked(Duration(seconds=5.0))
    taken = Capture()
    ring.activate(taken)
    for n in range(depth + 11, depth + 41):
        publisher.publish(Int64(data=n))
        time.sleep(0.002)
    _settle(publisher, taken, depth + 40)
    assert [e.seq for e in taken] == list(range(11, depth + 41))


def test_a_burst_beyond_the_history_is_reported_as_a_gap(
    ring: Ring, publisher: Publisher, tmp_path: Path,
) -> None:
    # A publisher that was blocked and catches up sends faster than any reader takes: DDS
    # keeps what fits the history and drops the oldest. Whatever is dropped must show as an
    # input gap with its exact range, never vanish.
    segments = SegmentStore(tmp_path / 'store', 'node')
    rlog = RecoveryLog(segments, {}, publishers=ring.publisher_count)
    publisher.publish(Int64(data=0))  # publication sequence number 1
    publisher.wait_for_all_acked(Duration(seconds=5.0))
    ring.activate(rlog)
    _settle(publisher, rlog.entries, 1)
    for n in range(1, 401):
        publisher.publish(Int64(data=n))
    _settle(publisher, rlog.entries, 401)
    seqs = [e.seq for e in rlog.entries]
    assert seqs == sorted(set(seqs)) and seqs[-1] == 401
    missing = sorted(set(range(1, 402)) - set(seqs))
    reported = [n for g in rlog.gaps for n in range(g.first, g.last + 1)]
    assert missing, 'the burst fitted the history: nothing was tested'  # 400 in ~3 ms vs 26
    assert reported == missing
    assert all(g.publishers == 1 for g in rlog.gaps)


def test_a_ring_on_the_supervisors_context_stays_passive_and_leaves_the_context_up(
    ros_domain: int,
) -> None:
    # The supervisor hands its own context over, so the ring's readers join its participant.
    # Its executor (spinning the supervisor's node) must not take the ring's messages, and
    # shutting the ring down must not shut the supervisor's context.
    from rclpy.executors import SingleThreadedExecutor

    owner = Context()
    rclpy.init(context=owner, domain_id=ros_domain)
    sup_node = Node('supervisor_like', context=owner)
    sup_executor = SingleThreadedExecutor(context=owner)
    sup_executor.add_node(sup_node)
    ctx = RingContext(owner)
    ring = Ring(ctx, 'node')
    ring.ensure([SPEC])
    pub_node = Node('burst_publisher', context=owner)
    pub = pub_node.create_publisher(Int64, SPEC.topic, QoSProfile(depth=100))
    try:
        deadline = time.monotonic() + 10.0
        while ring.publisher_count(SPEC.topic) < 1 or pub.get_subscription_count() < 1:
            assert time.monotonic() < deadline, 'ring reader and publisher never matched'
            time.sleep(0.01)
        for n in range(1, 6):
            pub.publish(Int64(data=n))
        pub.wait_for_all_acked(Duration(seconds=5.0))
        for _ in range(5):
            sup_executor.spin_once(timeout_sec=0.05)
        taken = Capture()
        ring.activate(taken)
        assert [e.seq for e in taken] == [1, 2, 3, 4, 5]
        for topic in ring.topics.values():
            topic.destroy()
        ctx.shutdown()
        assert owner.ok()
    finally:
        sup_executor.shutdown(timeout_sec=1.0)
        owner.try_shutdown()


def test_a_second_activation_hands_over_only_the_newest_depth(
    ring: Ring, publisher: Publisher,
) -> None:
    # What the first activation took (retained: DDS no longer holds it) and what DDS kept
    # since: together they are the last `depth` messages, never more. Handing over older ones
    # gave issue 21's recovery messages the node had applied long before, outside every
    # window it could check.
    depth = ring_depth(SPEC)
    taken = Capture()
    ring.activate(taken)
    for n in range(1, depth + 1):
        publisher.publish(Int64(data=n))
    _settle(publisher, taken, depth)
    ring.deactivate()
    for n in range(depth + 1, depth + 21):
        publisher.publish(Int64(data=n))
    publisher.wait_for_all_acked(Duration(seconds=5.0))
    again = Capture()
    ring.activate(again)
    assert [e.seq for e in again] == list(range(21, depth + 21))


def test_each_message_carries_its_publishers_gid(ros_domain: int, ring: Ring) -> None:
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    node = Node('two_publishers', context=ctx)
    pubs = [node.create_publisher(Int64, SPEC.topic, QoSProfile(depth=100)) for _ in range(2)]
    try:
        deadline = time.monotonic() + 10.0
        while ring.publisher_count(SPEC.topic) < 2 or any(
                pub.get_subscription_count() < 1 for pub in pubs):
            assert time.monotonic() < deadline, 'ring reader and publishers never matched'
            time.sleep(0.01)
        for n in range(1, 6):
            for k, pub in enumerate(pubs):
                pub.publish(Int64(data=100 * k + n))
        for pub in pubs:
            pub.wait_for_all_acked(Duration(seconds=5.0))
        taken = Capture()
        ring.activate(taken)
    finally:
        node.destroy_node()
        ctx.try_shutdown()
    by_publisher: dict[bytes | None, list[int]] = {}
    for e in taken:
        by_publisher.setdefault(e.publisher, []).append(e.seq)
    assert len(by_publisher) == 2 and all(p is not None and len(p) == 16 for p in by_publisher)
    assert sorted(by_publisher.values()) == [[1, 2, 3, 4, 5], [1, 2, 3, 4, 5]]


def test_nodes_reading_a_topic_alike_share_one_reader(ros_domain: int) -> None:
    # In a stack most nodes read /odom and /scan with the same QoS: one DDS reader serves all of
    # them, and each node's activation still gets the newest `depth` messages, whichever node's
    # activation took them from DDS. A node with a shallower queue shares it and is handed only
    # its own depth (its window absorbs no more); one with a deeper queue than the reader's
    # history has its own reader.
    ctx = RingContext(domain_id=ros_domain)
    first, second, other = Ring(ctx, 'first'), Ring(ctx, 'second'), Ring(ctx, 'other')
    small = Ring(ctx, 'small')
    other_spec = InputSpec(SPEC.topic, SPEC.msgtype, True, False, 50)
    small_spec = InputSpec(SPEC.topic, SPEC.msgtype, True, False, 5)
    first.ensure([SPEC])
    second.ensure([SPEC])
    other.ensure([other_spec])
    small.ensure([small_spec])
    pub_ctx = Context()
    rclpy.init(context=pub_ctx, domain_id=ros_domain)
    pub_node = Node('shared_publisher', context=pub_ctx)
    pub = pub_node.create_publisher(Int64, SPEC.topic, QoSProfile(depth=1000))
    depth = ring_depth(SPEC)
    try:
        assert ctx.reader_count == 2
        assert len(list(ctx.node.subscriptions)) == 2
        deadline = time.monotonic() + 10.0
        while (any(r.publisher_count(SPEC.topic) < 1 for r in (first, second, other, small))
               or pub.get_subscription_count() < 2):
            assert time.monotonic() < deadline, 'ring readers and publisher never matched'
            time.sleep(0.01)
        for n in range(1, 11):
            pub.publish(Int64(data=n))
        pub.wait_for_all_acked(Duration(seconds=5.0))
        taken_first = Capture()
        first.activate(taken_first)
        assert [e.seq for e in taken_first] == list(range(1, 11))
        # While the first node's view is active, its messages are taken from DDS as they come;
        # the second node's view still holds them.
        for n in range(11, depth + 21):
            pub.publish(Int64(data=n))
            time.sleep(0.002)  # no burst beyond the history: that is another test
        _settle(pub, taken_first, depth + 20)
        assert [e.seq for e in taken_first] == list(range(1, depth + 21))
        taken_second = Capture()
        second.activate(taken_second)
        assert [e.seq for e in taken_second] == list(range(21, depth + 21))
        # Both active: each new message reaches both, once.
        pub.publish(Int64(data=0))
        _settle(pub, taken_second, depth + 21)
        assert taken_first[-1].seq == taken_second[-1].seq == depth + 21
        assert [e.seq for e in taken_first].count(depth + 21) == 1
        # One node leaving keeps the reader for the other; the last one removes it.
        first.deactivate()
        for topic in first.topics.values():
            topic.destroy()
        assert ctx.reader_count == 2
        pub.publish(Int64(data=0))
        _settle(pub, taken_second, depth + 22)
        assert taken_first[-1].seq == depth + 21
        for topic in second.topics.values():
            topic.destroy()
        assert ctx.reader_count == 2  # the shallow node keeps the shared reader
        taken_small = Capture()
        small.activate(taken_small)
        assert ring_depth(small_spec) < ring_depth(SPEC)
        assert [e.seq for e in taken_small] == list(range(depth + 23 - ring_depth(small_spec),
                                                          depth + 23))
        for topic in small.topics.values():
            topic.destroy()
        assert ctx.reader_count == 1
        assert len(list(ctx.node.subscriptions)) == 1
        # The reader of the other QoS kept its own history all along.
        taken_other = Capture()
        other.activate(taken_other)
        assert ring_depth(other_spec) > depth + 22  # so it holds every message sent
        assert [e.seq for e in taken_other] == list(range(1, depth + 23))
    finally:
        for ring in (first, second, small, other):
            for topic in ring.topics.values():
                topic.destroy()
        pub_node.destroy_node()
        pub_ctx.try_shutdown()
        ctx.shutdown()


def test_a_message_taken_during_another_nodes_activation_reaches_both(
    ros_domain: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Two nodes sharing a reader, struck together: the first one's view is active, a message
    # arrives, and the second one activates before the ring's thread has taken it (under load,
    # it had not). Both must get it, once each. It once went to the second node's backlog only,
    # and the first node's recovery reported it as never having reached the host.
    ctx = RingContext(domain_id=ros_domain)
    first, second = Ring(ctx, 'first'), Ring(ctx, 'second')
    first.ensure([SPEC])
    second.ensure([SPEC])
    reader = first.topics[SPEC.topic].reader
    pub_ctx = Context()
    rclpy.init(context=pub_ctx, domain_id=ros_domain)
    pub_node = Node('racing_publisher', context=pub_ctx)
    pub = pub_node.create_publisher(Int64, SPEC.topic, QoSProfile(depth=1000))
    try:
        deadline = time.monotonic() + 10.0
        while first.publisher_count(SPEC.topic) < 1 or pub.get_subscription_count() < 1:
            assert time.monotonic() < deadline, 'ring reader and publisher never matched'
            time.sleep(0.01)
        pub.publish(Int64(data=1))
        pub.wait_for_all_acked(Duration(seconds=5.0))
        taken_first = Capture()
        first.activate(taken_first)
        assert [e.seq for e in taken_first] == [1]
        # The ring's thread is late: it takes nothing until the second node has activated.
        late = threading.Event()
        monkeypatch.setattr(reader, 'take_new', late.wait)
        pub.publish(Int64(data=2))
        pub.wait_for_all_acked(Duration(seconds=5.0))
        taken_second = Capture()
        second.activate(taken_second)
        monkeypatch.undo()  # the thread takes again: message 2 is still in DDS
        late.set()
        _settle(pub, taken_second, 2)
        _settle(pub, taken_first, 2)
        assert [e.seq for e in taken_first] == [1, 2]
        assert [e.seq for e in taken_second] == [1, 2]
    finally:
        for ring in (first, second):
            for topic in ring.topics.values():
                topic.destroy()
        pub_node.destroy_node()
        pub_ctx.try_shutdown()
        ctx.shutdown()
