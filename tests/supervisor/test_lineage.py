"""What may enter the recovery log R (lineage.Admission), driven with overlapping sources.

The sources of one recovery overlap by design: the newest checkpoint's windows, the node's
segments after its cut (an earlier R among them), the ring's backlog (messages taken in an
earlier activation, what DDS holds) and the ring's later messages. Whatever the overlap, R
must hold each identity at most once, only above what the node has of the same publisher, and
everything above it that the ring saw.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from rory_runtime.log import LogEntry, SegmentStore, read_segment
from rory_runtime.protocol import MessageId
from rory_runtime.supervisor.lineage import Admission, SequenceWatch, Verdict
from rory_runtime.supervisor.recovery import RecoveryLog

A = b'A' * 16
B = b'B' * 16
TOPIC = '/odom'


def msg(publisher: bytes, seq: int, recv_ns: int | None = None, topic: str = TOPIC) -> LogEntry:
    """One publisher's message: its source stamps grow with its sequence numbers."""
    base = 1_000_000_000 if publisher == A else 5_000_000
    source = base + seq * 20_000_000
    return LogEntry(topic, 'std_msgs/msg/Int64', source + 1_000 if recv_ns is None else recv_ns,
                    source, seq, b'', publisher)


def idents(*entries: LogEntry) -> set[MessageId]:
    return {e.ident for e in entries}


def judge_all(admission: Admission, backlog: list[LogEntry],
              later: Sequence[LogEntry] = ()) -> list[LogEntry]:
    admission.learn(backlog)
    admitted = [e for e in backlog if admission.judge(e) == Verdict.NEW]
    admitted += [e for e in later if admission.judge(e) == Verdict.NEW]
    return admitted


def test_stale_entries_of_an_earlier_activation_are_not_admitted_again() -> None:
    # Issue 21: the ring kept what it took in the first recovery (A 20..60). Long after, the
    # node's newest checkpoint window holds A 80..100 and its segments A 101..150; at the next
    # crash the ring holds the stale entries and A 140..160. The stale ones lie outside every
    # window the node could check; only A's mark (150, learnt from A 141..150) keeps them out.
    window = [msg(A, s) for s in range(80, 101)]
    logged = [msg(A, s) for s in range(101, 151)]
    admission = Admission({TOPIC: idents(*window, *logged)})
    backlog = [msg(A, s) for s in range(20, 61)] + [msg(A, s) for s in range(140, 161)]
    assert judge_all(admission, backlog) == [msg(A, s) for s in range(151, 161)]
    assert admission.high == {(TOPIC, A): 160}
    assert admission.dropped_known == 11
    assert admission.never_delivered_summary() == {TOPIC: {'count': 41, 'seqs': '20-60'}}


def test_messages_only_the_ring_got_before_the_nodes_first_are_never_delivered() -> None:
    # Issue 21's EKF: the ring matched the publisher first and took A 1-2; the node's reader
    # began at A 3 and logged through 10. Replaying 1-2 after 10 would apply them out of
    # order, and the node never had them in a run without a crash.
    admission = Admission({TOPIC: idents(*(msg(A, s) for s in range(3, 11)))})
    admitted = judge_all(admission, [msg(A, s) for s in range(1, 11)], [msg(A, 11)])
    assert admitted == [msg(A, 11)]
    assert admission.never_delivered == {TOPIC: [1, 2]}


def test_two_publishers_in_lockstep_are_judged_each_against_its_own_mark() -> None:
    # Same sequence numbers, same rate: a per-topic mark would drop B's 45 (below A's 45).
    known = idents(*(msg(A, s) for s in range(1, 46)), *(msg(B, s) for s in range(1, 45)))
    admission = Admission({TOPIC: known})
    backlog = sorted([msg(A, s) for s in range(40, 51)] + [msg(B, s) for s in range(40, 51)],
                     key=lambda e: e.recv_ns)
    admitted = judge_all(admission, backlog)
    assert [(e.publisher, e.seq) for e in admitted if e.publisher == A] == [
        (A, s) for s in range(46, 51)]
    assert [(e.publisher, e.seq) for e in admitted if e.publisher == B] == [
        (B, s) for s in range(45, 51)]
    assert admission.never_delivered == {}


def test_a_publisher_the_node_has_nothing_of_is_admitted_whole() -> None:
    admission = Admission({TOPIC: idents(*(msg(A, s) for s in range(1, 11)))})
    assert judge_all(admission, [msg(B, s) for s in range(1, 6)]) == [
        msg(B, s) for s in range(1, 6)]


def test_a_later_known_message_raises_the_mark_for_what_follows() -> None:
    # The ring's reader lagged: it takes A 9-10 (known) after the activation, then A 5 again
    # (a re-matched transient-local reader is sent the publisher's history once more).
    admission = Admission({TOPIC: idents(*(msg(A, s) for s in range(1, 11)))})
    admitted = judge_all(admission, [], [msg(A, 9), msg(A, 10), msg(A, 11), msg(A, 5)])
    assert admitted == [msg(A, 11)]
    assert admission.dropped_known == 3


def test_an_identity_admitted_once_is_known_to_every_later_source() -> None:
    known: dict[str, set[MessageId]] = {}
    admission = Admission(known)
    assert judge_all(admission, [msg(A, 1), msg(A, 2)], [msg(A, 2), msg(A, 3)]) == [
        msg(A, 1), msg(A, 2), msg(A, 3)]
    assert known == {TOPIC: idents(msg(A, 1), msg(A, 2), msg(A, 3))}
    # a second activation's backlog repeats them all
    assert judge_all(admission, [msg(A, 1), msg(A, 2), msg(A, 3), msg(A, 4)]) == [msg(A, 4)]


def test_entries_without_a_publisher_are_judged_by_identity_alone() -> None:
    plain = [LogEntry(TOPIC, 'std_msgs/msg/Int64', s, s, s, b'') for s in range(1, 6)]
    admission = Admission({TOPIC: {plain[3].ident}})
    assert judge_all(admission, plain) == [plain[0], plain[1], plain[2], plain[4]]
    assert admission.high == {}


def test_topics_are_judged_apart() -> None:
    admission = Admission({'/a': idents(msg(A, 5, topic='/a'))})
    backlog = [msg(A, 3, topic='/a'), msg(A, 5, topic='/a'), msg(A, 3, topic='/b')]
    assert judge_all(admission, backlog) == [msg(A, 3, topic='/b')]
    assert admission.never_delivered == {'/a': [3]}


def test_gaps_are_per_publisher() -> None:
    # Two publishers interleave; each is checked against its own numbers (a per-topic check
    # saw a "gap" at every switch between them).
    admission = Admission({TOPIC: idents(msg(A, 10), msg(B, 3))})
    watch = SequenceWatch()
    backlog = [msg(A, 10), msg(B, 3)]
    admission.learn(backlog)
    watch.seed(admission, {TOPIC: 10}, backlog)
    for entry in [*backlog, msg(A, 11), msg(B, 4), msg(A, 12), msg(B, 7), msg(A, 13)]:
        watch.track(entry, admission.judge(entry))
    assert [(g.first, g.last) for g in watch.gaps] == [(5, 6)]


def test_recovery_log_writes_only_what_admission_lets_in(tmp_path: Path) -> None:
    segments = SegmentStore(tmp_path / 'store', 'node')
    known = idents(*(msg(A, s) for s in range(3, 11)))
    rlog = RecoveryLog(segments, {TOPIC: known})
    rlog.add_backlog([msg(A, s) for s in range(1, 11)])
    rlog.add(msg(A, 11))
    rlog.seal()
    rlog.add(msg(A, 12))
    stored = [(e.topic, e.source_ns, e.seq) for e in read_segment(segments.path(rlog.number))]
    assert stored == [(TOPIC, msg(A, 11).source_ns, 11)]
    assert [e.seq for e in rlog.relay] == [12]
    assert rlog.never_delivered() == {TOPIC: {'count': 2, 'seqs': '1-2'}}
    assert rlog.summary()[TOPIC]['never_delivered'] == 2


# -- the invariant, over drawn histories ----------------------------------------------------


@st.composite
def histories(draw: st.DrawFn) -> dict[str, Any]:
    """Two publishers' streams; per publisher where the node's reader began and how far the
    node logged; the checkpoint's cut and window; the ring's depth (the window is larger, as
    protocol.window_size makes it); an early capture that repeats part of the backlog; later
    messages, some of them repeats."""
    sent, began, logged = {}, {}, {}
    for publisher in (A, B):
        n = draw(st.integers(0, 60))
        sent[publisher] = n
        began[publisher] = draw(st.integers(1, max(1, n)))
        logged[publisher] = draw(st.integers(began[publisher] - 1, n))
    depth = draw(st.integers(1, 50))
    return {
        'sent': sent, 'began': began, 'logged': logged, 'depth': depth,
        'window': depth + draw(st.integers(0, 30)),
        'cut': draw(st.floats(0.0, 1.0)),
        'early': draw(st.integers(0, 20)),
        'later': draw(st.integers(0, 20)),
        'repeats': draw(st.lists(st.integers(0, 200), max_size=10)),
    }


@settings(max_examples=300, deadline=None)
@given(histories())
def test_r_holds_each_identity_once_above_what_the_node_has(history: dict[str, Any]) -> None:
    sent, began, logged = history['sent'], history['began'], history['logged']
    # The stream as the ring received it: both publishers interleaved by receive time; the
    # last `later` messages arrive after the activation.
    stream = sorted((msg(p, s, recv_ns=s * 1_000 + (0 if p == A else 500))
                     for p in (A, B) for s in range(1, sent[p] + 1)), key=lambda e: e.recv_ns)
    split = max(0, len(stream) - history['later'])
    before, after = stream[:split], stream[split:]

    def pub(e: LogEntry) -> bytes:
        assert e.publisher is not None
        return e.publisher

    node_has = [e for e in before if began[pub(e)] <= e.seq <= logged[pub(e)]]
    # What the store shows of it: the checkpoint's window (the last `window` before its cut)
    # and every message after the cut.
    cut_at = int(len(node_has) * history['cut'])
    known = idents(*node_has[max(0, cut_at - history['window']):])
    # The ring's backlog: the newest `depth` messages it had, led by an early capture that
    # repeats some of them; later messages, with repeats of what the ring had (a relay added
    # again, a transient-local history sent again).
    backlog = before[max(0, split - history['depth']):]
    backlog = backlog[:history['early']] + backlog
    had = backlog + after
    repeats = [had[i % len(had)] for i in history['repeats']] if had else []
    admission = Admission({TOPIC: set(known)})
    admitted = judge_all(admission, backlog, after + repeats)

    seen = [e.ident for e in admitted]
    assert len(seen) == len(set(seen)), 'an identity admitted twice'
    for publisher in (A, B):
        mine = [e.seq for e in admitted if e.publisher == publisher]
        assert mine == sorted(mine), "R out of its publisher's order"
        mark = max((e.seq for e in node_has if e.publisher == publisher), default=0)
        assert all(s > mark for s in mine), 'at or below what the node has'
        # Nothing the ring had above the node's mark is left out.
        held = {e.seq for e in backlog + after if e.publisher == publisher}
        assert {s for s in held if s > mark} <= set(mine)
