"""What the supervisor tells the rest of the robot: ``/diagnostics`` and ``/rory/events``.

``/diagnostics`` (diagnostic_msgs/DiagnosticArray, once a second, as diagnostic_updater
publishes) carries one status per supervised node, named ``rory: <node>``, so that
rqt_robot_monitor, diagnostic_aggregator and any fleet dashboard show it beside the robot's
other health. Its level follows the node's state: OK while it runs (or has finished), WARN while
it starts or recovers, ERROR once the supervisor has given up; a running node is WARN while
its checkpoints are overdue and ERROR while they fail. Its values: state, pid,
incarnation, method, crashes, last recovery time, age of the last checkpoint, warm standby.

``/rory/events`` (std_msgs/String, one JSON object per message, reliable, the last 100 kept for
late subscribers) carries every record of ``events.jsonl`` as it is written: state changes,
spawns, recoveries with their S1-S4 times, checkpoints, quarantined messages.
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from typing import Any, Final

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from .health import NodeHealth
from .states import NodeState

# /diagnostics is one topic for the whole robot (aggregators listen there); the events are the
# supervisor's own, relative to its namespace: /rory/events, or /robot1/rory/events.
DIAGNOSTICS_TOPIC: Final = '/diagnostics'
EVENTS_TOPIC: Final = 'rory/events'
DIAGNOSTICS_PERIOD: Final = 1.0
"""Seconds between /diagnostics messages (diagnostic_updater's default rate)."""

EVENTS_QOS: Final = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=100,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)

_WARN_STATES: Final = frozenset({
    NodeState.STOPPED, NodeState.STARTING, NodeState.ARMING, NodeState.CRASHED,
    NodeState.BACKOFF, NodeState.RESTORING, NodeState.REPLAYING, NodeState.GATED,
    NodeState.STOPPING,
})


OK: Final[bytes] = bytes(DiagnosticStatus.OK)
WARN: Final[bytes] = bytes(DiagnosticStatus.WARN)
ERROR: Final[bytes] = bytes(DiagnosticStatus.ERROR)


def level_of(state: NodeState) -> bytes:
    """The diagnostic level for a node in ``state``."""
    if state == NodeState.FATAL:
        return ERROR
    if state in _WARN_STATES:
        return WARN
    return OK


def _message(health: NodeHealth) -> str:
    if health.state == NodeState.RUNNING and health.checkpoint_error is not None:
        return f'running; checkpoints failing: {health.checkpoint_error}'
    if health.state == NodeState.RUNNING and health.checkpoint_overdue_s is not None:
        age_s = health.last_checkpoint_age_s
        since = 'none yet' if age_s is None else f'last {age_s:.0f} s ago'
        return (f'running; checkpoints overdue ({since}; the interval follows the node\'s '
                'ROS time)')
    if health.state == NodeState.FATAL:
        if health.fatal_reason:
            return f'gave up: {health.fatal_reason}'
        return f'gave up after {health.crashes} crashes; the safe state is held'
    if health.state == NodeState.GATED:
        return (f'recovered, outputs muted and the safe state held until '
                f'{health.gate_service} is called')
    if health.state == NodeState.EXITED:
        return 'finished (exit status 0)'
    if health.state == NodeState.RUNNING:
        return 'running' if health.crashes == 0 else f'running; recovered {health.crashes}x'
    return health.state.value.lower()


def _number(value: float | None, digits: int = 1) -> str:
    return '' if value is None else f'{value:.{digits}f}'


def node_status(health: NodeHealth, namespace: str = '/') -> DiagnosticStatus:
    """The DiagnosticStatus of one node of a supervisor in ``namespace``.

    Named ``rory: <node>``, or ``rory: robot1/<node>`` under ``/robot1``: robots that share a
    DDS network share /diagnostics, and the same config gives each robot the same node ids.
    """
    qualified = f'{namespace.strip("/")}/{health.node}'.lstrip('/')
    values = {
        'state': health.state.value,
        'method': health.method,
        'pid': '' if health.pid is None else str(health.pid),
        'incarnation': str(health.incarnation),
        'crashes': str(health.crashes),
        'last recovery (ms)': _number(health.last_recovery_ms),
        'last recovery age (s)': _number(health.last_recovery_age_s),
        'last checkpoint age (s)': _number(health.last_checkpoint_age_s),
        'warm standby': health.standby,
    }
    if health.freshness is not None:
        verdict = health.freshness
        values['last restore: checkpoint age (s)'] = _number(verdict.age_s)
        for keys, label in ((verdict.restored, 'restored'), (verdict.reset, 'reset (stale)'),
                            (verdict.kept_stale, 'kept stale'),
                            (verdict.refused, 'refused (stale)')):
            values[f'last restore: {label}'] = ', '.join(keys)
    level = level_of(health.state)
    if health.state == NodeState.RUNNING:
        # A node that runs but cannot be recovered to now is not OK.
        if health.checkpoint_error is not None:
            level = ERROR
        elif health.checkpoint_overdue_s is not None:
            level = WARN
    return DiagnosticStatus(
        level=level,
        name=f'rory: {qualified}',
        message=_message(health),
        hardware_id=qualified,
        values=[KeyValue(key=k, value=v) for k, v in values.items()],
    )


class Reporter:
    """Publishes /diagnostics and /rory/events from the supervisor's own ROS node."""

    def __init__(self, ros_node: Node) -> None:
        self._node = ros_node
        self._diagnostics = ros_node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._events = ros_node.create_publisher(String, EVENTS_TOPIC, EVENTS_QOS)
        self._next = 0.0

    def event(self, record: dict[str, Any]) -> None:
        """Publish one event record (as written to events.jsonl)."""
        self._events.publish(String(data=json.dumps(record, sort_keys=True)))

    def due(self, now: float) -> bool:
        """Whether the next /diagnostics message is due (and, if so, schedule the one after)."""
        if now < self._next:
            return False
        self._next = now + DIAGNOSTICS_PERIOD
        return True

    def diagnostics(self, nodes: Iterable[NodeHealth]) -> None:
        """Publish one DiagnosticArray with a status per node."""
        namespace = self._node.get_namespace()
        array = DiagnosticArray(status=[node_status(h, namespace) for h in nodes])
        array.header.stamp = self._node.get_clock().now().to_msg()
        self._diagnostics.publish(array)
