"""The guard of tests/conftest.py: a test not marked ros starts no ROS process. What it starts
may import rclpy and serialize messages, but joining ROS fails at rcl's init."""

from __future__ import annotations

import subprocess
import sys

CHILD = '''
import rclpy
from rclpy.serialization import serialize_message
from std_msgs.msg import Int64
assert serialize_message(Int64(data=7))
print('imported and serialized', flush=True)
rclpy.init()
print('joined ROS', flush=True)
'''


def test_a_process_started_by_an_unmarked_test_cannot_join_ros() -> None:
    done = subprocess.run([sys.executable, '-c', CHILD], capture_output=True, text=True,
                          timeout=60, check=False)
    assert done.returncode != 0
    assert done.stdout == 'imported and serialized\n'
    assert 'ROS_DOMAIN_ID is not an integral number' in done.stderr
