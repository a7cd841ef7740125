"""The rclpy nodes RORY makes for itself in the supervisor and the standby: hidden, and with
no service or publisher beyond what rclpy always makes.

Every service and publisher of a node is DDS endpoints that every participant on the robot
discovers and keeps; a default rclpy node brings ~16 (parameter services, /rosout,
~/get_type_description). RORY's own nodes answer none of them: the ring's readers only need a
node for their graph queries, and a standby's placeholder only keeps its participant alive.
"""

from __future__ import annotations

from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter


def quiet_node(name: str, context: Context | None = None) -> Node:
    """A node with nothing but its parameter-events publisher (rclpy always makes it): no
    parameter services, no /rosout, no ~/get_type_description. Name it with a leading
    underscore to hide it from node lists."""
    return Node(name, context=context, start_parameter_services=False, enable_rosout=False,
                parameter_overrides=[Parameter('start_type_description_service', value=False)])
