"""Safe-state actions on a real rclpy node: shared, scoped, held until the last node is back."""

from __future__ import annotations

import textwrap
import time
from collections.abc import Iterator
from pathlib import Path
from typing import cast

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions
from std_msgs.msg import Bool

from rory_runtime.supervisor.config import load_config
from rory_runtime.supervisor.safety import LATCHED_QOS, SafeState

CONFIG = """\
nodes:
  - {name: amcl1, command: [x]}
  - {name: navigator1, command: [x]}
  - {name: amcl2, command: [x]}
safe_state:
  - {topic: robot1/e_stop, type: std_msgs/msg/Bool, hold: {data: true},
     release: {data: false}, nodes: [amcl1, navigator1]}
  - {topic: robot2/e_stop, type: std_msgs/msg/Bool, hold: {data: true},
     release: {data: false}, nodes: [amcl2]}
  - {topic: /fleet/any_recovering, type: std_msgs/msg/Bool, hold: {data: true},
     release: {data: false}, rate: 50}
"""


class _Heard:
    def __init__(self, node: Node, topic: str) -> None:
        self.values: list[bool] = []
        node.create_subscription(Bool, topic, lambda m: self.values.append(cast(Bool, m).data),
                                 LATCHED_QOS)


@pytest.fixture
def node(ros_domain: int) -> Iterator[Node]:
    context = Context()
    rclpy.init(args=['t', '--ros-args', '-r', '__ns:=/site'], context=context,
               domain_id=ros_domain, signal_handler_options=SignalHandlerOptions.NO)
    made = Node('rory_supervisor', context=context, start_parameter_services=False)
    yield made
    made.destroy_node()
    context.try_shutdown()


def _spin(node: Node, seconds: float) -> None:
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.02)
    executor.remove_node(node)


def test_each_action_is_held_while_a_node_in_its_scope_recovers(
    node: Node, tmp_path: Path
) -> None:
    path = tmp_path / 'fleet.yaml'
    path.write_text(textwrap.dedent(CONFIG))
    notes: list[tuple[str, str, str]] = []
    safety = SafeState(node, load_config(path), lambda *note: notes.append(note))
    robot1 = _Heard(node, '/site/robot1/e_stop')
    robot2 = _Heard(node, '/site/robot2/e_stop')
    fleet = _Heard(node, '/fleet/any_recovering')
    _spin(node, 1.0)  # discovery

    safety.hold('amcl1')
    safety.hold('navigator1')  # both of robot 1 down at once: held once
    assert safety.held_topics() == ['/site/robot1/e_stop', '/fleet/any_recovering']
    _spin(node, 0.5)
    assert robot1.values == [True] and robot2.values == []
    assert fleet.values[:1] == [True] and len(fleet.values) > 5  # republished at its rate

    safety.release('amcl1')  # navigator1 still recovering: nothing released
    _spin(node, 0.3)
    assert robot1.values == [True] and fleet.values[-1] is True

    safety.release('navigator1')
    assert not safety.held and safety.holders == set()
    _spin(node, 0.3)
    assert robot1.values == [True, False] and robot2.values == []
    assert fleet.values[-1] is False
    repeats = len(fleet.values)
    _spin(node, 0.2)
    assert len(fleet.values) == repeats, 'the rated hold stopped with the release'

    assert notes == [('amcl1', 'held', '/site/robot1/e_stop'),
                     ('amcl1', 'held', '/fleet/any_recovering'),
                     ('navigator1', 'released', '/site/robot1/e_stop'),
                     ('navigator1', 'released', '/fleet/any_recovering')]
    safety.hold('amcl2')
    _spin(node, 0.3)  # (depth 1: a release right behind the hold would replace it unread)
    safety.release('amcl2')
    _spin(node, 0.3)
    assert robot2.values == [True, False] and robot1.values == [True, False]
