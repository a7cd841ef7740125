"""What ``target_faults`` leaves behind for a wrong run, and its explicit cases."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.serialization import serialize_message

from rory_eval.faults import target_faults
from rory_eval.targets import TARGETS


def _pose(stamp_ns: int, x: float) -> bytes:
    msg = PoseWithCovarianceStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp_ns, 1_000_000_000)
    msg.pose.pose.position.x = x
    msg.pose.pose.orientation.w = 1.0
    return bytes(serialize_message(msg))


def test_differences_list_only_the_stamps_that_differ_or_are_absent(tmp_path: Path) -> None:
    reference = {1_000_000_000: _pose(1_000_000_000, 1.0),
                 1_100_000_000: _pose(1_100_000_000, 2.0),
                 1_200_000_000: _pose(1_200_000_000, 3.0)}
    crashed = {1_000_000_000: reference[1_000_000_000],
               1_100_000_000: _pose(1_100_000_000, 2.5)}
    path = tmp_path / 'differences.txt'
    target_faults.write_differences(reference, crashed, TARGETS['amcl'], path)
    lines = path.read_text().splitlines()
    assert lines[1:] == [
        '1.100 | pose.pose.position.x: 2.0 -> 2.5',
        '1.200 | crashed has none',
    ]
    saved = json.loads((tmp_path / 'outputs.json').read_text())
    assert bytes.fromhex(saved['reference']['1200000000']) == reference[1_200_000_000]
    assert set(saved['crashed']) == {'1000000000', '1100000000'}


def test_then_needs_a_strike_and_faults_are_checked(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        target_faults.main(['--then', 'raise', '0.5'])
    assert '--then needs --strike' in capsys.readouterr().err
    with pytest.raises(SystemExit):
        target_faults.main(['--strike', 'SIGFOO', '3'])
    assert "unknown fault 'SIGFOO'" in capsys.readouterr().err


@pytest.mark.parametrize(('argv', 'said'), [
    (['--strike', 'hang', 'soon'], "--strike hang soon: 'soon' is not seconds"),
    (['--strike', 'hang', '3', '--then', 'raise', '-1'], 'seconds must be 0 or more'),
    (['--repeat', '0'], '0 is not 1 or more'),
])
def test_bad_case_options_are_refused_by_name(argv: list[str], said: str,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        target_faults.main(argv)
    assert said in capsys.readouterr().err


def test_the_clock_waits_for_each_targets_own_inputs() -> None:
    from rory_eval.faults.target_crash import sensor_readers

    assert sensor_readers(TARGETS['depth_mapper']) == {'/camera/depth/points': 2, '/odom': 2}
    assert sensor_readers(TARGETS['grid_slam']) == {'/scan': 2}
