"""Faults during recovery: a poison message is found, quarantined and skipped."""

from __future__ import annotations

import base64
import json
from pathlib import Path

import pytest
from rclpy.serialization import deserialize_message
from std_msgs.msg import Int64

from rory_eval.scenario import Program, run

pytestmark = pytest.mark.ros

FAULTS = Path(__file__).parent / 'faults'


def test_poison_message_is_quarantined_and_the_node_goes_on(
    tmp_path: Path, ros_domain: int
) -> None:
    program = Program(FAULTS, FAULTS / 'keyvars.yaml', 'poison.py', '/state', 'fragile')
    result = run('rory', (), tmp_path, domain_id=ros_domain, count=150, program=program,
                 timeout=120)
    kinds = [e['kind'] for e in result.events]
    exits = [e for e in result.events if e['kind'] == 'exit']
    # 1: dies live on 77; 2: dies again when the replay reaches 77 -> quarantined; 3: goes on
    assert len(exits) == 2, result.log[-3000:]
    assert kinds.count('quarantined') == 1
    quarantined = next(e for e in result.events if e['kind'] == 'quarantined')
    record = json.loads(Path(quarantined['path']).read_text())
    assert record['topic'] == '/numbers'
    message = deserialize_message(base64.b64decode(record['cdr_base64']), Int64)
    assert message.data == 77
    # nothing else lost, nothing doubled, 77 skipped
    assert result.state['history'] == [n for n in range(1, 151) if n != 77]
    states = [e['new'] for e in result.events if e['kind'] == 'state']
    # the node was running when the harness stopped it (the stop itself may or may not be in
    # the events yet): never FATAL
    assert [s for s in states if s not in ('STOPPING', 'STOPPED')][-1] == 'RUNNING', states
    assert 'FATAL' not in states


def test_a_hung_node_is_killed_recovered_and_its_hanging_message_quarantined(
    tmp_path: Path, ros_domain: int
) -> None:
    program = Program(FAULTS, FAULTS / 'keyvars.yaml', 'hang.py', '/state', 'stuck',
                      settings=(('hang_timeout', 1.5),))
    result = run('rory', (), tmp_path, domain_id=ros_domain, count=150, program=program,
                 timeout=120)
    hangs = [e for e in result.events if e['kind'] == 'hang']
    # 1: hangs live on 77; 2: hangs again when the replay reaches 77 -> quarantined; 3: goes on
    assert len(hangs) == 2, result.log[-3000:]
    assert all(h['topic'] == '/numbers' and h['waiting_for'] == 'heartbeat' for h in hangs)
    assert all(1.5 < h['stalled_s'] < 3.0 for h in hangs)
    exits = [e for e in result.events if e['kind'] == 'exit']
    assert [e['code'] for e in exits] == [-9, -9]
    assert [e['kind'] for e in result.events].count('quarantined') == 1
    assert result.state['history'] == [n for n in range(1, 151) if n != 77]
    # SIGUSR1 before the kill: the node printed where it hung
    assert 'in on_number' in result.log, result.log[-3000:]
