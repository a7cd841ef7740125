"""Our log segments opened by a reader nobody here wrote: Foxglove's `mcap` + `mcap-ros2-support`.

The messages must decode from the schemas the file itself carries (no ROS installation needed),
and a segment cut short by a SIGKILL (no summary, no footer) must still stream.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosReliability, QosTime
from rosbags.rosbag2 import Reader
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Int64

from rory_runtime.log import SegmentWriter
from rory_runtime.qos import to_rosbag


def _write(segment: Path, *, close: bool) -> SegmentWriter:
    writer = SegmentWriter(segment)
    for i in range(5):
        writer.write('/count', 'std_msgs/msg/Int64', 1_000 + 2 * i, 7, i + 1,
                     serialize_message(Int64(data=i * 11)))
        scan = LaserScan(ranges=[float(i), 2.0, 3.0], range_max=10.0)
        scan.header.frame_id = 'laser'
        writer.write('/scan', 'sensor_msgs/msg/LaserScan', 1_001 + 2 * i, 8, i + 1,
                     serialize_message(scan))
    if close:
        writer.close()
    return writer


def test_a_closed_segment_decodes_from_its_own_schemas(tmp_path: Path) -> None:
    segment = tmp_path / 'seg'
    _write(segment, close=True)
    with (segment / 'seg.mcap').open('rb') as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        assert summary.statistics.message_count == 10
        schemas = {s.name: s for s in summary.schemas.values()}
        assert schemas['std_msgs/msg/Int64'].encoding == 'ros2msg'
        assert b'float32[] ranges' in schemas['sensor_msgs/msg/LaserScan'].data
        channels = {c.topic: c for c in summary.channels.values()}
        assert channels['/scan'].message_encoding == 'cdr'
        assert 'offered_qos_profiles' in channels['/scan'].metadata
        decoded = [(channel.topic, message.log_time, message.publish_time, message.sequence, ros)
                   for _, channel, message, ros in reader.iter_decoded_messages()]
    counts = [d for d in decoded if d[0] == '/count']
    assert [ros.data for *_, ros in counts] == [0, 11, 22, 33, 44]
    # RORY's message identity sits in the standard fields: publish_time is the publisher's
    # source timestamp, sequence its sequence number.
    assert [(c[2], c[3]) for c in counts] == [(7, k) for k in range(1, 6)]
    scans = [ros for topic, *_, ros in decoded if topic == '/scan']
    assert scans[2].header.frame_id == 'laser' and list(scans[2].ranges) == [2.0, 2.0, 3.0]


def test_a_segment_cut_short_by_a_crash_still_streams(tmp_path: Path) -> None:
    segment = tmp_path / 'seg'
    writer = _write(segment, close=False)  # as a SIGKILL leaves it: no summary, no footer
    try:
        with (segment / 'seg.mcap').open('rb') as stream:
            # Not seekable to a summary: read it front to back, as a crash log must be read.
            reader = make_reader(_Unseekable(stream), decoder_factories=[DecoderFactory()])
            got = []
            # Every message comes out, in file (= receive) order; then the reader reports the
            # missing footer. (Sorting by log time would read to the end before yielding.)
            with pytest.raises(EndOfFile):
                for _, channel, _, ros in reader.iter_decoded_messages(log_time_order=False):
                    got.append((channel.topic, ros))
        assert len(got) == 10
        assert [ros.data for topic, ros in got if topic == '/count'] == [0, 11, 22, 33, 44]
    finally:
        writer.close()


class _Unseekable:
    """A file the reader may only read forward."""

    def __init__(self, stream: object) -> None:
        self._stream = stream

    def read(self, size: int = -1) -> bytes:
        data: bytes = self._stream.read(size)  # type: ignore[attr-defined]
        return data

    def seekable(self) -> bool:
        return False


def test_the_publishers_qos_is_stored_as_ros2_bag_record_stores_it(tmp_path: Path) -> None:
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    asked: list[str] = []

    def offered() -> list[Qos]:
        asked.append('/map')
        return [to_rosbag(latched)]

    segment = tmp_path / 'seg'
    writer = SegmentWriter(segment)
    for i in range(3):
        writer.write('/map', 'std_msgs/msg/Int64', 1_000 + i, 7, i + 1,
                     serialize_message(Int64(data=i)), offered_qos=offered)
    writer.close()
    assert asked == ['/map']  # once per topic and segment, not per message
    with Reader(segment) as bag:
        (connection,) = bag.connections
        (qos,) = connection.ext.offered_qos_profiles  # type: ignore[union-attr]
    assert qos.durability == QosDurability.TRANSIENT_LOCAL
    assert qos.reliability == QosReliability.RELIABLE
    assert qos.history == QosHistory.KEEP_LAST and qos.depth == 1
    assert qos.deadline == QosTime(0, 0)
