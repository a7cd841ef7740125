"""A test's in-process ROS helpers leave nothing behind in the pytest worker: a later test given
the same domain (each worker cycles through its span of ids, tests/conftest.py) must not hear
what they published. A shut-down context keeps its DDS participant while a node of it is
undestroyed; the sim probe's latched /e_stop (True after the e-stop test) once engaged a safe
state in an integrator run that had no crash (issue 35)."""

from __future__ import annotations

import time

import pytest
import rclpy
from conftest import Probe
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Bool

from sim.qos import LATCHED_QOS

pytestmark = pytest.mark.ros


def test_a_closed_probe_leaves_no_latched_e_stop_behind(ros_domain: int) -> None:
    probe = Probe(ros_domain)
    probe.send_e_stop(True)
    time.sleep(0.2)
    probe.close()

    # The next test in this domain, in this worker process.
    context = Context()
    rclpy.init(context=context, domain_id=ros_domain,
               signal_handler_options=SignalHandlerOptions.NO)
    node = Node('next_test_observer', context=context)
    heard: list[bool] = []
    node.create_subscription(Bool, '/e_stop', lambda m: heard.append(m.data), LATCHED_QOS)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        # A live latched writer on this host is matched and heard within ~0.1 s here; 1.5 s
        # leaves room for a loaded machine.
        end = time.monotonic() + 1.5
        while time.monotonic() < end and not heard:
            executor.spin_once(timeout_sec=0.05)
    finally:
        executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        context.try_shutdown()
    assert heard == []
