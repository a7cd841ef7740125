"""Common mode: one message that every reader of a topic dies on (issue 38).

Three nodes read /numbers under one supervisor, and each raises on the same number. All three
crash on it live, recover, crash again when their replay reaches it, and come back with it
quarantined: each ends exactly as a run without a crash that skipped that one message, and
each node's ``recovered`` event and its quarantine record name the message. Real processes
throughout (rory_eval/faults/common_mode_campaign.py runs them): three instrumented
integrators that raise on the number their ``poison`` parameter names, ``rory supervise``, a
publisher of 1..N, whose sequence number is the number it sends.
"""

from __future__ import annotations

import base64
from pathlib import Path
from typing import Any

import pytest
from rclpy.serialization import deserialize_message
from std_msgs.msg import Int64

from rory_eval.faults.common_mode_campaign import NODES, TOPIC, run_common_mode

pytestmark = pytest.mark.ros

COUNT = 150  # 3 s at 50 Hz
POISON = 40  # 0.8 s in: both crashes and recoveries come while numbers still arrive


def _one(events: list[dict[str, Any]], kind: str, why: str) -> dict[str, Any]:
    """The one event of ``kind`` among ``events``."""
    found = [e for e in events if e['kind'] == kind]
    assert len(found) == 1, f'{len(found)} {kind} events: {found}\n{why}'
    return found[0]


def test_three_nodes_dying_on_one_message_all_come_back_with_it_quarantined(
    tmp_path: Path, ros_domain: int
) -> None:
    run = run_common_mode(tmp_path, ros_domain, count=COUNT, poison=POISON)
    for node in NODES:
        why = f'{node}:\n{run.log_tail}'
        mine = [e for e in run.events if e.get('node') == node]
        kinds = [e['kind'] for e in mine]
        # Crashed live on the number, then again when the replay reached it; never gave up.
        exits = [e for e in mine if e['kind'] == 'exit']
        assert [e['incarnation'] for e in exits] == [1, 2], why
        assert 'fatal' not in kinds, why
        died_on = _one(mine, 'died_on', why)
        assert (died_on['incarnation'], died_on['topic'], died_on['seq']) == (1, TOPIC, POISON)
        quarantined = _one(mine, 'quarantined', why)
        assert (quarantined['topic'], quarantined['seq']) == (TOPIC, POISON), why
        assert Path(quarantined['path']).parent == tmp_path / 'store-rory' / node / 'quarantine'
        message = (TOPIC, quarantined['source_ns'], POISON)
        # One recovery covers both crashes and names the message, both times it killed the node
        # and as the one set aside.
        recovered = _one(mine, 'recovered', why)
        assert recovered['crashes'] == 2, why
        assert [(m['incarnation'], m['topic'], m['source_ns'], m['seq'])
                for m in recovered['died_on']] == [(1, *message), (2, *message)], why
        assert [(m['topic'], m['source_ns'], m['seq'], m['path'])
                for m in recovered['quarantined']] == [(*message, quarantined['path'])], why
        # Its quarantine folder holds that one message, its CDR bytes the number.
        assert len(run.quarantine[node]) == 1, run.quarantine[node]
        record = run.quarantine[node][0]
        assert (record['node'], record['topic'], record['source_ns'], record['seq']) == (
            node, *message)
        assert deserialize_message(base64.b64decode(record['cdr_base64']), Int64).data == POISON
        # Exactly a run without a crash that skipped that one message: in order, none twice.
        skipped = [n for n in range(1, COUNT + 1) if n != POISON]
        state = run.states[node]
        assert (state['history'], state['count'], state['total']) == (
            skipped, len(skipped), sum(skipped)), why
