"""The topic the supervisor answers a node on: its name and QoS.

Topics (``<node>`` is the node's id from the supervisor configuration; ``/rory`` is the
*channel*, the supervisor's namespace followed by ``rory``, so that two supervisors on one DDS
network, e.g. one per robot under ``-r __ns:=/robot1``, never share a topic):

``/rory/<node>/replay``  supervisor -> node, ``std_msgs/msg/UInt8MultiArray`` carrying an
    envelope. This is the node's *shadow topic*: recorded messages of every input topic travel
    on it, multiplexed, so that the node receives them in exactly the recorded order (DDS keeps
    no order across topics, one shadow topic per input would not). Reliable, volatile, keep-all.

The QoS (:data:`REPLAY_QOS`, an rclpy ``QoSProfile``) is made at its first use, so that a
module that only reads statuses or envelopes (the supervisor's decisions) loads no rclpy; it is
typed ``Any`` so that type-checking the protocol does not load rclpy either.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Final

DEFAULT_CHANNEL: Final = '/rory'


def channel(namespace: str) -> str:
    """The channel of a supervisor whose node is in ``namespace`` (``/robot1/rory``)."""
    return f'{namespace.rstrip("/")}{DEFAULT_CHANNEL}'


def replay_topic(node_id: str, incarnation: int, channel: str = DEFAULT_CHANNEL) -> str:
    """The shadow topic of one process of a node.

    One per incarnation: the supervisor's writer is keep-all and reliable, so a reader it is
    matched with holds every sample until that reader acknowledges it, and a reader of a
    process that died (it stays matched until its DDS lease runs out) never does. A new
    process's reader is on a topic no dead reader was ever on.
    """
    return f'{channel}/{node_id}/replay_{incarnation}'


REPLAY_QOS: Any  # an rclpy QoSProfile
"""The shadow topic's QoS. Keep-all: a reliable writer then resends whatever a late-matching
reader has not acknowledged, and nothing is dropped however far the node falls behind. Made at
its first read (:func:`__getattr__`)."""


def _replay_qos() -> Any:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    return QoSProfile(
        history=HistoryPolicy.KEEP_ALL,
        depth=1000,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.VOLATILE,
    )


if not TYPE_CHECKING:  # hidden from mypy, which would take every unknown name for an attribute
    def __getattr__(name: str) -> Any:
        """:data:`REPLAY_QOS`, made once, at its first read (then a plain attribute)."""
        if name == 'REPLAY_QOS':
            qos = globals()['REPLAY_QOS'] = _replay_qos()
            return qos
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
