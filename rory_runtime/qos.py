"""The QoS a topic's publishers offer, in rosbag2's terms, for the log's ``offered_qos_profiles``.

``ros2 bag record`` stores, per topic, the QoS profiles of the publishers it recorded, so that
``ros2 bag play`` can offer the same (a latched map must be replayed latched). RORY's logs do
the same from the node's own view of the graph when a segment first logs a topic.
"""

from __future__ import annotations

from rclpy.node import Node
from rclpy.qos import QoSProfile
from rosbags.interfaces import (
    Qos,
    QosDurability,
    QosHistory,
    QosLiveliness,
    QosReliability,
    QosTime,
)

_INFINITE = QosTime(2147483647, 4294967295)  # how rosbag2 writes an unset (infinite) duration
_MAX_SEC = 2147483647


def _time(nanoseconds: int) -> QosTime:
    if nanoseconds <= 0:
        return QosTime(0, 0)
    sec, nsec = divmod(nanoseconds, 1_000_000_000)
    return _INFINITE if sec >= _MAX_SEC else QosTime(sec, nsec)


def _enum(kind: type[QosHistory] | type[QosReliability] | type[QosDurability]
          | type[QosLiveliness], value: int) -> object:
    try:
        return kind(int(value))
    except ValueError:
        return kind.UNKNOWN


def to_rosbag(profile: QoSProfile) -> Qos:
    """An rclpy QoS profile as rosbags' Qos (rmw's numbering is the same on both sides)."""
    return Qos(
        history=_enum(QosHistory, profile.history),  # type: ignore[arg-type]
        depth=int(profile.depth),
        reliability=_enum(QosReliability, profile.reliability),  # type: ignore[arg-type]
        durability=_enum(QosDurability, profile.durability),  # type: ignore[arg-type]
        deadline=_time(profile.deadline.nanoseconds),
        lifespan=_time(profile.lifespan.nanoseconds),
        liveliness=_enum(QosLiveliness, profile.liveliness),  # type: ignore[arg-type]
        liveliness_lease_duration=_time(profile.liveliness_lease_duration.nanoseconds),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions),
    )


def offered_qos(node: Node, topic: str) -> list[Qos]:
    """The QoS of every publisher of ``topic`` the node currently sees (none: an empty list)."""
    try:
        infos = node.get_publishers_info_by_topic(topic)
    except Exception:
        return []
    return [to_rosbag(info.qos_profile) for info in infos]
