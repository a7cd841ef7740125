"""What /diagnostics says about a node, state by state (no ROS: the messages are built only)."""

from __future__ import annotations

from typing import Any

import pytest
from diagnostic_msgs.msg import DiagnosticStatus

from rory_runtime.freshness import Verdict
from rory_runtime.supervisor.diagnostics import level_of, node_status
from rory_runtime.supervisor.health import NodeHealth
from rory_runtime.supervisor.states import NodeState


def _health(state: NodeState, **kw: object) -> NodeHealth:
    fields: dict[str, Any] = dict(
        node='mapper', state=state, method='rory', pid=42, incarnation=3, crashes=2,
        last_recovery_ms=143.25, last_recovery_age_s=12.0, last_checkpoint_age_s=0.4,
        standby='ready')
    fields.update(kw)
    return NodeHealth(**fields)


@pytest.mark.parametrize(('state', 'level'), [
    (NodeState.RUNNING, DiagnosticStatus.OK),
    (NodeState.EXITED, DiagnosticStatus.OK),
    (NodeState.STARTING, DiagnosticStatus.WARN),
    (NodeState.CRASHED, DiagnosticStatus.WARN),
    (NodeState.BACKOFF, DiagnosticStatus.WARN),
    (NodeState.RESTORING, DiagnosticStatus.WARN),
    (NodeState.REPLAYING, DiagnosticStatus.WARN),
    (NodeState.GATED, DiagnosticStatus.WARN),
    (NodeState.FATAL, DiagnosticStatus.ERROR),
])
def test_the_level_follows_the_state(state: NodeState, level: bytes) -> None:
    assert level_of(state) == level


def test_every_state_has_a_level() -> None:
    for state in NodeState:
        assert level_of(state) in (DiagnosticStatus.OK, DiagnosticStatus.WARN,
                                   DiagnosticStatus.ERROR)


def test_a_running_node_says_how_often_it_was_recovered() -> None:
    status = node_status(_health(NodeState.RUNNING))
    assert status.name == 'rory: mapper' and status.hardware_id == 'mapper'
    assert status.level == DiagnosticStatus.OK
    assert status.message == 'running; recovered 2x'
    values = {kv.key: kv.value for kv in status.values}
    assert values == {
        'state': 'RUNNING', 'method': 'rory', 'pid': '42', 'incarnation': '3', 'crashes': '2',
        'last recovery (ms)': '143.2', 'last recovery age (s)': '12.0',
        'last checkpoint age (s)': '0.4', 'warm standby': 'ready',
    }


def test_a_node_given_up_on_is_an_error_that_says_the_safe_state_is_held() -> None:
    status = node_status(_health(NodeState.FATAL, pid=None, crashes=6))
    assert status.level == DiagnosticStatus.ERROR
    assert 'gave up after 6 crashes' in status.message and 'safe state' in status.message
    assert {kv.key: kv.value for kv in status.values}['pid'] == ''


def test_a_node_at_its_release_gate_says_which_service_releases_it() -> None:
    status = node_status(_health(NodeState.GATED, gate_service='/rory/mapper/release'))
    assert status.level == DiagnosticStatus.WARN
    assert status.message == ('recovered, outputs muted and the safe state held until '
                              '/rory/mapper/release is called')


def test_a_refused_start_says_why() -> None:
    status = node_status(_health(NodeState.FATAL, fatal_reason='checkpoint too old for pose'))
    assert status.level == DiagnosticStatus.ERROR
    assert status.message == 'gave up: checkpoint too old for pose'


def test_the_last_restore_says_what_was_restored_reset_and_kept_stale() -> None:
    verdict = Verdict(age_s=12.345, clock='system', restored=['map', 'count'], reset=['pose'],
                      kept_stale=['goal'])
    values = {kv.key: kv.value for kv in node_status(_health(NodeState.RUNNING,
                                                             freshness=verdict)).values}
    assert values['last restore: checkpoint age (s)'] == '12.3'
    assert values['last restore: restored'] == 'map, count'
    assert values['last restore: reset (stale)'] == 'pose'
    assert values['last restore: kept stale'] == 'goal'
    assert values['last restore: refused (stale)'] == ''


def test_unknowns_are_empty_not_zero() -> None:
    status = node_status(_health(NodeState.STARTING, last_recovery_ms=None,
                                 last_recovery_age_s=None, last_checkpoint_age_s=None))
    values = {kv.key: kv.value for kv in status.values}
    assert values['last recovery (ms)'] == '' and values['last checkpoint age (s)'] == ''
    assert status.message == 'starting'


def test_a_supervisor_in_a_namespace_names_its_nodes_with_it() -> None:
    # Robots on one DDS network share /diagnostics, and one config gives each the same ids.
    assert node_status(_health(NodeState.RUNNING)).name == 'rory: mapper'
    status = node_status(_health(NodeState.RUNNING), '/robot1')
    assert status.name == 'rory: robot1/mapper' and status.hardware_id == 'robot1/mapper'


def test_a_running_node_whose_checkpoints_are_overdue_is_a_warning() -> None:
    status = node_status(_health(NodeState.RUNNING, last_checkpoint_age_s=None,
                                 checkpoint_overdue_s=0.7))
    assert status.level == DiagnosticStatus.WARN
    assert status.message == ("running; checkpoints overdue (none yet; the interval follows "
                              "the node's ROS time)")
    late = node_status(_health(NodeState.RUNNING, last_checkpoint_age_s=31.0,
                               checkpoint_overdue_s=25.0))
    assert 'last 31 s ago' in late.message


def test_a_running_node_whose_checkpoints_fail_is_an_error_until_one_succeeds() -> None:
    failing = node_status(_health(
        NodeState.RUNNING, checkpoint_error="checkpoint skipped: variable 'seen' is a defaultdict",
        checkpoint_overdue_s=4.0))
    assert failing.level == DiagnosticStatus.ERROR
    assert failing.message == ("running; checkpoints failing: checkpoint skipped: variable "
                               "'seen' is a defaultdict")
    assert node_status(_health(NodeState.RUNNING)).level == DiagnosticStatus.OK


def test_checkpoint_health_does_not_change_other_states() -> None:
    status = node_status(_health(NodeState.FATAL, checkpoint_error='checkpoint skipped: x'))
    assert status.level == DiagnosticStatus.ERROR and 'gave up' in status.message
