"""recording_bench: the sequence check, the judge, counting a log, and a short real run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from rosbags.interfaces import QosReliability
from rosbags.rosbag2 import Reader

from rory_eval.bench.recording_bench import (
    STREAMS,
    RunResult,
    Usage,
    check_sequence,
    count_recorded,
    judge,
    main,
)
from rory_runtime import protocol
from rory_runtime.log import SegmentStore

IDLE = Usage(cpu_seconds=0.0, wall_seconds=1.0, peak_rss_mb=0.0)


def _load(published: dict[str, int], acked: bool = True) -> dict[str, object]:
    return {'topics': {t: {'published': n, 'acked': acked} for t, n in published.items()}}


ALL = {topic: 3 for topic, _, _ in STREAMS}


def test_a_contiguous_run_from_one_is_complete() -> None:
    seq = check_sequence([3, 1, 2])
    assert (seq.count, seq.first, seq.last, seq.gaps, seq.duplicates) == (3, 1, 3, (), 0)
    assert seq.complete(3)
    assert seq.describe() == '1-3'


def test_gaps_are_reported_as_inclusive_runs() -> None:
    seq = check_sequence([1, 2, 5, 6, 8])
    assert seq.gaps == ((3, 4), (7, 7))
    assert not seq.complete(8)
    assert seq.describe() == '1-8, missing 3-4, 7'


def test_repeats_and_a_missing_start_or_end_are_not_complete() -> None:
    assert check_sequence([1, 2, 2, 3]).duplicates == 1
    assert not check_sequence([1, 2, 2, 3]).complete(3)
    assert not check_sequence([2, 3]).complete(3)  # the first message never recorded
    assert not check_sequence([1, 2]).complete(3)  # the last one
    assert '1 repeated' in check_sequence([1, 1]).describe()


def test_nothing_recorded() -> None:
    seq = check_sequence([])
    assert (seq.first, seq.last, seq.describe()) == (None, None, 'none')
    assert seq.complete(0)
    assert not seq.complete(1)


def test_many_gaps_are_summarised() -> None:
    seq = check_sequence(range(1, 20, 2))
    assert len(seq.gaps) == 9
    assert seq.describe().endswith('(+6 more)')


def test_the_judge_names_each_drop_with_its_topic() -> None:
    received = dict(ALL, **{'/map': 2})
    run = RunResult('rory', _load(ALL), received, IDLE,
                    recorded=dict(ALL, **{'/odom': 2}),
                    sequences={t: check_sequence(range(1, 4)) for t in ALL}
                    | {'/odom': check_sequence([1, 3])})
    problems = judge(run)
    assert 'rory: /map: the node received 2 of 3' in problems
    assert 'rory: /odom: 2 of 3 recorded' in problems
    assert 'rory: /odom: recorded sequence numbers 1-3, missing 2, expected 1-3' in problems
    assert len(problems) == 3


def test_the_judge_flags_unacknowledged_messages_and_passes_a_clean_run() -> None:
    assert judge(RunResult('bare', _load(ALL), dict(ALL), IDLE)) == []
    problems = judge(RunResult('bare', _load(ALL, acked=False), dict(ALL), IDLE))
    assert len(problems) == len(STREAMS)
    assert all('not all acknowledged' in p for p in problems)


def test_count_recorded_reads_every_segment(tmp_path: Path) -> None:
    store = SegmentStore(tmp_path, 'sink')
    with store.open(1) as seg:
        for seq in (1, 2):
            seg.write('/odom', 'nav_msgs/msg/Odometry', seq, seq, seq, b'\0' * 10)
        seg.write('/map', 'nav_msgs/msg/OccupancyGrid', 3, 3, 1, b'\0' * 100)
    # The next segment left as a killed writer leaves it: no summary, no metadata.yaml.
    seg2 = store.open(2)
    seg2.write('/odom', 'nav_msgs/msg/Odometry', 4, 4, 4, b'\0' * 12)
    counts, sizes, sequences = count_recorded(tmp_path, 'sink')
    assert counts == {'/odom': 3, '/map': 1}
    assert sizes == {'/odom': 12, '/map': 100}
    assert sequences['/odom'].describe() == '1-4, missing 3'
    seg2.close()


@pytest.mark.ros
@pytest.mark.timeout(90)
def test_recording_keeps_up_with_the_sensor_load(tmp_path: Path, ros_domain: int) -> None:
    # The full load at full rates, 4 s: scans, odometry, clouds and 4 MB maps.
    out = tmp_path / 'out'
    status = main(['--seconds', '4', '--out', str(out), '--domain', str(ros_domain)])
    report = (out / 'recording.md').read_text()
    assert status == 0, report
    result = json.loads((out / 'recording.json').read_text())
    for topic, _, rate in STREAMS:
        published = result['rory']['load']['topics'][topic]['published']
        assert published == round(4 * rate)
        assert result['bare']['received'][topic] == result['bare']['load']['topics'][topic][
            'published']
        assert result['rory']['received'][topic] == published
        assert result['rory']['recorded'][topic] == published, report
        assert result['rory']['sequences'][topic] == f'1-{published}'
    # Each segment says, as ros2 bag record would, what QoS the publishers offered.
    segments = SegmentStore(out / 'store', 'sensor_sink')
    for n in segments.numbers():
        with Reader(segments.path(n)) as bag:
            for connection in bag.connections:
                if not protocol.is_input_topic(connection.topic):
                    continue  # a tick or clock record: no DDS topic, nothing offered
                offered = connection.ext.offered_qos_profiles  # type: ignore[union-attr]
                assert offered, f'segment {n} {connection.topic}: no offered QoS'
                assert {q.reliability for q in offered} == {QosReliability.RELIABLE}
