"""Tests of absorbed identities, the recovery log R and the timing breakdown."""

from __future__ import annotations

from pathlib import Path

import pytest
from rclpy.serialization import serialize_message
from std_msgs.msg import Int64

from rory_runtime.log import LogEntry, SegmentStore, read_segment
from rory_runtime.store import Checkpoint, CheckpointStore
from rory_runtime.supervisor.lineage import InputGap
from rory_runtime.supervisor.recovery import (
    GAP_HOLD_S,
    Recovery,
    RecoveryLog,
    Timings,
    absorbed_identities,
)

NODE = 'integrator'
INT64 = 'std_msgs/msg/Int64'


def int64(value: int) -> bytes:
    return bytes(serialize_message(Int64(data=value)))


def entry(topic: str, source_ns: int, seq: int, recv_ns: int | None = None) -> LogEntry:
    recv = source_ns + 1_000 if recv_ns is None else recv_ns
    return LogEntry(topic, INT64, recv, source_ns, seq, int64(seq))


@pytest.fixture
def segments(tmp_path: Path) -> SegmentStore:
    return SegmentStore(tmp_path / 'store', NODE)


@pytest.fixture
def checkpoints(tmp_path: Path) -> CheckpointStore:
    return CheckpointStore(tmp_path / 'store', NODE, keep=5)


def add_each(rlog: RecoveryLog, entries: list[LogEntry]) -> None:
    """As the ring delivers after its backlog: one message at a time."""
    for e in entries:
        rlog.add(e)


def write_segment(segments: SegmentStore, n: int, entries: list[LogEntry]) -> None:
    with segments.open(n) as writer:
        for e in entries:
            writer.write(e.topic, e.msgtype, e.recv_ns, e.source_ns, e.seq, e.data)


def write_checkpoint(
    checkpoints: CheckpointStore,
    seq: int,
    cut: int | None,
    windows: dict[str, list[tuple[int, int]]],
) -> Path:
    return checkpoints.write(
        Checkpoint(
            node=NODE,
            seq=seq,
            incarnation=1,
            created_ns=1_700_000_000_000_000_000,
            manifest='sha256:test',
            method='rory',
            cut=cut,
            windows=windows,
            vars_blob=b'',
        )
    )


# --------------------------------------------------------------------------- absorbed_identities


def test_absorbed_identities_empty_store(
    segments: SegmentStore, checkpoints: CheckpointStore
) -> None:
    assert absorbed_identities(checkpoints, segments) == {}


def test_absorbed_identities_without_checkpoint_are_all_segments(
    segments: SegmentStore, checkpoints: CheckpointStore
) -> None:
    write_segment(segments, 1, [entry('/a', 10, 1), entry('/b', 20, 1)])
    write_segment(segments, 2, [entry('/a', 11, 2)])
    write_segment(segments, 3, [entry('/b', 21, 2), entry('/a', 12, 3)])
    assert absorbed_identities(checkpoints, segments) == {
        '/a': {(10, 1), (11, 2), (12, 3)},
        '/b': {(20, 1), (21, 2)},
    }


def test_absorbed_identities_union_checkpoint_windows_and_segments_after_cut(
    segments: SegmentStore, checkpoints: CheckpointStore
) -> None:
    write_segment(segments, 1, [entry('/a', 10, 1)])
    write_segment(segments, 2, [entry('/a', 11, 2), entry('/b', 20, 1)])
    write_segment(segments, 3, [entry('/a', 12, 3), entry('/c', 30, 1)])
    write_checkpoint(checkpoints, 1, cut=2, windows={'/a': [(11, 2)], '/d': [(40, 7)]})
    assert absorbed_identities(checkpoints, segments) == {
        '/a': {(11, 2), (12, 3)},  # (10, 1) is in segment 1, before the cut, not in a window
        '/c': {(30, 1)},
        '/d': {(40, 7)},
    }


def test_absorbed_identities_use_the_newest_checkpoint(
    segments: SegmentStore, checkpoints: CheckpointStore
) -> None:
    write_segment(segments, 1, [entry('/a', 10, 1)])
    write_segment(segments, 2, [entry('/a', 11, 2)])
    write_checkpoint(checkpoints, 1, cut=0, windows={'/old': [(1, 1)]})
    write_checkpoint(checkpoints, 2, cut=1, windows={'/a': [(10, 1)]})
    assert absorbed_identities(checkpoints, segments) == {'/a': {(10, 1), (11, 2)}}


def test_absorbed_identities_skip_an_unreadable_newest_checkpoint(
    segments: SegmentStore, checkpoints: CheckpointStore
) -> None:
    write_segment(segments, 1, [entry('/a', 10, 1)])
    write_segment(segments, 2, [entry('/a', 11, 2)])
    write_segment(segments, 3, [entry('/a', 12, 3)])
    write_checkpoint(checkpoints, 1, cut=1, windows={'/a': [(10, 1)], '/w1': [(5, 5)]})
    newest = write_checkpoint(checkpoints, 2, cut=2, windows={'/w2': [(6, 6)]})
    data = bytearray(newest.read_bytes())
    data[len(data) // 2] ^= 0xFF
    newest.write_bytes(bytes(data))
    assert absorbed_identities(checkpoints, segments) == {
        '/a': {(10, 1), (11, 2), (12, 3)},
        '/w1': {(5, 5)},
    }


def test_absorbed_identities_checkpoint_without_cut_counts_every_segment(
    segments: SegmentStore, checkpoints: CheckpointStore
) -> None:
    write_segment(segments, 1, [entry('/a', 10, 1)])
    write_checkpoint(checkpoints, 1, cut=None, windows={'/a': [(9, 9)]})
    assert absorbed_identities(checkpoints, segments) == {'/a': {(9, 9), (10, 1)}}


# --------------------------------------------------------------------------- RecoveryLog


def test_recovery_log_opens_the_next_segment(segments: SegmentStore) -> None:
    write_segment(segments, 1, [entry('/a', 10, 1)])
    write_segment(segments, 2, [])
    rlog = RecoveryLog(segments, {})
    assert rlog.number == 3
    assert segments.path(3).is_dir()
    assert not rlog.sealed
    rlog.close()


def test_recovery_log_writes_new_entries_in_order(segments: SegmentStore) -> None:
    rlog = RecoveryLog(segments, {})
    added = [entry('/a', 10, 1), entry('/b', 5, 9), entry('/a', 11, 2), entry('/b', 6, 10)]
    for e in added:
        rlog.add(e)
    assert rlog.entries == added
    # Durable before sealing: a killed supervisor leaves a readable segment.
    assert list(read_segment(segments.path(rlog.number))) == added
    rlog.seal()
    assert list(read_segment(segments.path(rlog.number))) == added
    assert rlog.dropped_known == 0


def test_recovery_log_drops_identities_already_known(segments: SegmentStore) -> None:
    known = {'/a': {(10, 1), (11, 2)}}
    rlog = RecoveryLog(segments, known)
    rlog.add_backlog([entry('/a', 10, 1), entry('/a', 12, 3), entry('/a', 11, 2)])
    assert rlog.entries == [entry('/a', 12, 3)]
    assert rlog.dropped_known == 2
    rlog.seal()
    assert list(read_segment(segments.path(rlog.number))) == [entry('/a', 12, 3)]


def test_recovery_log_known_identities_are_per_topic(segments: SegmentStore) -> None:
    rlog = RecoveryLog(segments, {'/a': {(10, 1)}})
    rlog.add(entry('/b', 10, 1))
    assert rlog.entries == [entry('/b', 10, 1)]
    assert rlog.dropped_known == 0
    rlog.close()


def test_recovery_log_drops_an_entry_added_twice(segments: SegmentStore) -> None:
    rlog = RecoveryLog(segments, {})
    first = entry('/a', 10, 1, recv_ns=100)
    again = entry('/a', 10, 1, recv_ns=200)  # same identity, received again (ring + live)
    rlog.add(first)
    rlog.add(again)
    rlog.add(first)
    assert rlog.entries == [first]
    assert rlog.dropped_known == 2
    rlog.seal()
    assert list(read_segment(segments.path(rlog.number))) == [first]


def test_recovery_log_seal_closes_the_segment(segments: SegmentStore) -> None:
    rlog = RecoveryLog(segments, {})
    rlog.add(entry('/a', 10, 1))
    path = segments.path(rlog.number)
    assert not (path / 'metadata.yaml').exists()
    rlog.seal()
    assert rlog.sealed
    assert (path / 'metadata.yaml').is_file()
    rlog.seal()  # idempotent
    assert rlog.sealed


def test_recovery_log_empty_seal_closes_the_segment(segments: SegmentStore) -> None:
    rlog = RecoveryLog(segments, {})
    rlog.seal()
    path = segments.path(rlog.number)
    assert (path / 'metadata.yaml').is_file()
    assert list(read_segment(path)) == []


def test_recovery_log_close_seals(segments: SegmentStore) -> None:
    rlog = RecoveryLog(segments, {})
    rlog.close()
    assert rlog.sealed
    assert (segments.path(rlog.number) / 'metadata.yaml').is_file()


def test_recovery_log_after_seal_entries_go_to_relay(segments: SegmentStore) -> None:
    rlog = RecoveryLog(segments, {'/a': {(1, 1)}})
    logged = entry('/a', 10, 1)
    rlog.add(logged)
    rlog.seal()
    late = [entry('/a', 11, 2), entry('/b', 3, 3)]
    add_each(rlog, late)
    rlog.add(entry('/a', 11, 2))  # still deduplicated after the seal
    rlog.add(entry('/a', 1, 1))  # known before
    assert list(rlog.relay) == late
    assert rlog.entries == [logged]
    assert rlog.dropped_known == 2
    assert list(read_segment(segments.path(rlog.number))) == [logged]


def test_recovery_log_records_added_identities_as_known(segments: SegmentStore) -> None:
    known: dict[str, set[tuple[int, int]]] = {}
    rlog = RecoveryLog(segments, known)
    rlog.add(entry('/a', 10, 1))
    assert known == {'/a': {(10, 1)}}
    rlog.close()


# --------------------------------------------------------------------------- Timings


def test_timings_breakdown() -> None:
    t = Timings(
        crashed=100.0,
        s1_done=100.001,
        s2_done=100.003,
        spawned=100.010,
        hello=100.210,
        restore_ms=50.0,
        synced=100.260,
        release_sent=100.360,
        s4_done=100.380,
    )
    assert t.breakdown() == pytest.approx(
        {
            'total_ms': 380.0,
            's1_ms': 1.0,
            's2_ms': 2.0,
            'restart_ms': 150.0,
            'restore_ms': 50.0,
            'sync_ms': 50.0,
            'replay_ms': 100.0,
            's4_ms': 20.0,
        },
        abs=0.011,
    )


def test_timings_total_is_crash_to_s4_done() -> None:
    t = Timings(crashed=5.0, s4_done=7.5)
    assert t.breakdown()['total_ms'] == pytest.approx(2500.0)


def test_timings_unreached_steps_are_zero() -> None:
    assert Timings(crashed=1.0).breakdown() == {
        'total_ms': 0.0,
        's1_ms': 0.0,
        's2_ms': 0.0,
        'restart_ms': 0.0,
        'restore_ms': 0.0,
        'sync_ms': 0.0,
        'replay_ms': 0.0,
        's4_ms': 0.0,
    }


def test_timings_s4_without_release_counts_from_hello() -> None:
    """Methods without replay never send RELEASE."""
    t = Timings(crashed=0.0, spawned=1.0, hello=1.5, s4_done=1.75)
    assert t.breakdown()['s4_ms'] == pytest.approx(250.0)


def test_timings_restart_never_negative() -> None:
    t = Timings(crashed=0.0, spawned=1.0, hello=1.01, restore_ms=50.0)
    assert t.breakdown()['restart_ms'] == 0.0
    assert t.breakdown()['restore_ms'] == 50.0


def _numbers(seqs: range | list[int], topic: str = '/numbers') -> list[LogEntry]:
    return [entry(topic, 1_000_000 * s, s) for s in seqs]


def test_numbers_that_never_reached_the_host_are_a_gap_in_the_sequence(
    segments: SegmentStore,
) -> None:
    # The node logged 1..10; the ring's backlog repeats 6..10, then 11..20 and, after a
    # link outage longer than the DDS lease, 31..35: 21..30 never arrived.
    rlog = RecoveryLog(segments, {'/numbers': {e.ident for e in _numbers(range(1, 11))}})
    rlog.add_backlog(_numbers(range(6, 21)))
    assert rlog.gaps == []
    add_each(rlog, _numbers(range(31, 36)))
    rlog.seal()
    add_each(rlog, _numbers([36, 38]))  # after the release, in the relay: still seen
    assert [(g.topic, g.first, g.last, g.missing) for g in rlog.gaps] == [
        ('/numbers', 21, 30, 10), ('/numbers', 37, 37, 1)]
    assert rlog.gaps[0].to_json() == {'topic': '/numbers', 'first': 21, 'last': 30,
                                      'missing': 10}


def test_a_gap_keeps_the_publisher_count_of_the_moment_it_was_seen(
    segments: SegmentStore,
) -> None:
    # Judged later, the publisher may be gone (it finished and left): the count that says
    # whether the numbers are one publisher's is the one when the jump arrived.
    matched = {'/numbers': 1}
    rlog = RecoveryLog(segments, {'/numbers': {e.ident for e in _numbers(range(1, 11))}},
                       publishers=lambda topic: matched[topic])
    rlog.add_backlog(_numbers([11, 15]))
    matched['/numbers'] = 0
    assert [(g.first, g.last, g.publishers) for g in rlog.gaps] == [(12, 14, 1)]
    assert 'publishers' not in rlog.gaps[0].to_json()


def test_the_first_message_after_the_crash_is_checked_against_the_nodes_log(
    segments: SegmentStore,
) -> None:
    rlog = RecoveryLog(segments, {'/numbers': {e.ident for e in _numbers(range(1, 11))}})
    rlog.add_backlog(_numbers([14, 15]))
    assert [(g.first, g.last) for g in rlog.gaps] == [(11, 13)]


def test_a_restarted_publisher_starts_a_new_sequence_without_a_gap(
    segments: SegmentStore,
) -> None:
    rlog = RecoveryLog(segments, {'/numbers': {e.ident for e in _numbers(range(1, 51))}})
    restarted = [entry('/numbers', 9_000_000_000 + s, s) for s in (1, 2, 3)]
    add_each(rlog, restarted)
    assert rlog.gaps == []
    assert [e.seq for e in rlog.entries] == [1, 2, 3]


def test_the_summary_places_r_after_what_the_node_logged(segments: SegmentStore) -> None:
    # The node logged 1..10; R repeats 6..10 (dropped as known) and takes 11..20; after the
    # seal, 21 goes to the relay and is not part of R.
    rlog = RecoveryLog(segments, {'/numbers': {e.ident for e in _numbers(range(1, 11))}})
    rlog.add_backlog(_numbers(range(6, 21)))
    rlog.add(entry('/odom', 5_000_000, 7))
    rlog.seal()
    add_each(rlog, _numbers([21]))
    assert rlog.summary() == {
        '/numbers': {'logged_through': 10, 'entries': 10, 'first_seq': 11, 'last_seq': 20,
                     'never_delivered': 0},
        '/odom': {'logged_through': None, 'entries': 1, 'first_seq': 7, 'last_seq': 7,
                  'never_delivered': 0},
    }


# --------------------------------------------------------------------------- gaps and the handover
#
# After a link outage longer than the DDS lease the node's live reader may be matched with the
# publisher again before the ring: it then applies, before the first relayed message, what only
# it received, and names those in SWITCHED (live_only). The gap reported is what reached
# neither reader (issue 35).


class _Safety:
    def hold(self, node_id: str) -> None:
        pass

    def release(self, node_id: str) -> None:
        pass


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _recovery(segments: SegmentStore, checkpoints: CheckpointStore,
              clock: _Clock | None = None) -> Recovery:
    """A recovery whose R knows the node logged /numbers 1..10, took 11..15 and 17..20 before
    the release (16 never arrived), and relayed 31..35 after it (21..30 never reached R)."""
    rec = Recovery(node_id=NODE, crashed=0.0, crashed_ns=0, safety=_Safety(), ring=None,
                   segments=segments, checkpoints=checkpoints, clock=clock or _Clock())
    rec.rlog = RecoveryLog(segments, {'/numbers': {e.ident for e in _numbers(range(1, 11))}})
    rec.rlog.add_backlog(_numbers([*range(11, 16), *range(17, 21)]))
    rec.rlog.seal()
    add_each(rec.rlog, _numbers(range(31, 36)))
    return rec


def _spans(gaps: list[InputGap]) -> list[tuple[int, int]]:
    return [(g.first, g.last) for g in gaps]


def every(_gap: InputGap) -> bool:
    return True


def test_a_gap_seen_in_the_relay_waits_for_the_switch_and_leaves_out_what_the_node_had_live(
    segments: SegmentStore, checkpoints: CheckpointStore,
) -> None:
    rec = _recovery(segments, checkpoints)
    # Seen before the release: reported at once. Seen in the relay: the node may have some.
    assert _spans(rec.input_gaps(every)) == [(16, 16)]
    rec.on_switched('/numbers', live_only=range(25, 31))
    assert _spans(rec.input_gaps(every)) == [(16, 16), (21, 24)]
    assert rec.input_gaps(every)[1].to_json() == {'topic': '/numbers', 'first': 21,
                                                  'last': 24, 'missing': 4}


def test_what_the_node_had_live_may_split_a_gap_or_close_it(
    segments: SegmentStore, checkpoints: CheckpointStore,
) -> None:
    rec = _recovery(segments, checkpoints)
    rec.on_switched('/numbers', live_only=[22, 23, 27, 99])  # 99: no gap of R's
    assert _spans(rec.input_gaps(every)) == [(16, 16), (21, 21), (24, 26), (28, 30)]
    closed = _recovery(segments, checkpoints)
    closed.on_switched('/numbers', live_only=range(21, 31))
    assert _spans(closed.input_gaps(every)) == [(16, 16)]


def test_a_held_gap_is_reported_whole_once_it_waited_long_enough(
    segments: SegmentStore, checkpoints: CheckpointStore, caplog: pytest.LogCaptureFixture,
) -> None:
    # A handover that does not end (the publisher stopped): after GAP_HOLD_S the gap is
    # reported as the ring saw it, and stays so; what the node says later is logged.
    clock = _Clock()
    rec = _recovery(segments, checkpoints, clock)
    assert _spans(rec.input_gaps(every)) == [(16, 16)]
    clock.now += GAP_HOLD_S - 0.1
    assert _spans(rec.input_gaps(every)) == [(16, 16)]
    clock.now += 0.1
    assert _spans(rec.input_gaps(every)) == [(16, 16), (21, 30)]
    rec.on_switched('/numbers', live_only=range(25, 31))
    assert _spans(rec.input_gaps(every)) == [(16, 16), (21, 30)]
    assert 'of the gap reported before the topic switched (publication seq 21-30), 25-30 ' \
        "reached the node's live reader" in caplog.text


def test_a_held_gap_is_reported_whole_when_the_recovery_stops_before_the_switch(
    segments: SegmentStore, checkpoints: CheckpointStore,
) -> None:
    rec = _recovery(segments, checkpoints)
    rec.stop()  # the supervisor stops, or the node crashes during the handover
    assert _spans(rec.input_gaps(every)) == [(16, 16), (21, 30)]


def test_an_untrustworthy_gap_is_never_reported(
    segments: SegmentStore, checkpoints: CheckpointStore,
) -> None:
    rec = _recovery(segments, checkpoints)
    rec.stop()
    assert rec.input_gaps(lambda gap: gap.first != 21) == [rec.input_gaps(every)[0]]
