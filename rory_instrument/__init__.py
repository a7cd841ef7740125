"""rory-instrument: rewrites a ROS 2 node's source so it links against rory_runtime."""

from __future__ import annotations
