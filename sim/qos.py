"""The QoS of the simulator's topics, one profile per kind of topic.

Shared by the bridge (its publishers and the ``/cmd_vel`` reader) and the route driver (its
``/cmd_vel`` writer), so that both ends of a topic are made from the same profile.
"""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

SENSOR_QOS = QoSProfile(
    depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE,
    history=HistoryPolicy.KEEP_LAST,
)
"""Sensors, odometry, ground truth: reliable, volatile, keep last 10 (best-effort readers match)."""

CLOUD_QOS = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
"""Depth clouds: reliable, keep last 2 (a slow reader gets the newest, not a backlog)."""

CLOCK_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
"""/clock: reliable keep-last 1 (rclpy's time source reads it best-effort, which matches)."""

CMD_VEL_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
"""/cmd_vel: reliable, depth 10 (rclpy's default; a best-effort publisher would not match)."""

LATCHED_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""/e_stop, /ground_truth/map, /sim/info: reliable, transient local, depth 1."""

EVENT_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
"""/collisions: reliable, depth 100 (events must not be dropped)."""
