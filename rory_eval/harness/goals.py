"""Goals in the simulator's worlds as the navigator takes them."""

from __future__ import annotations

import math
from typing import Any


def goal_message(world: str, goal: str) -> Any:
    """The world's named goal as a geometry_msgs/PoseStamped in ``map``, stamped 0."""
    from geometry_msgs.msg import PoseStamped

    from sim.worlds import get_world

    pose = get_world(world).goals[goal]
    msg = PoseStamped()
    msg.header.frame_id = 'map'
    msg.pose.position.x = pose.x
    msg.pose.position.y = pose.y
    msg.pose.orientation.z = math.sin(pose.yaw / 2.0)
    msg.pose.orientation.w = math.cos(pose.yaw / 2.0)
    return msg
