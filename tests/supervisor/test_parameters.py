"""The supervisor's settings as ROS parameters of a real rclpy node (overrides as --ros-args)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from rory_runtime.errors import ParameterError
from rory_runtime.protocol import Method, ReplayPace
from rory_runtime.supervisor.config import SupervisorConfig, load_config
from rory_runtime.supervisor.parameters import NODE_SETTINGS, apply_parameters, own_ros_args

CONFIG = """\
nodes:
  - name: amcl
    command: [python, amcl.py]
    method: rory
    checkpoint_interval: 2.0
  - name: navigator
    command: [python, navigator.py]
    method: restart
    hang_timeout: null
store: state
"""


@pytest.fixture
def config(tmp_path: Path) -> SupervisorConfig:
    path = tmp_path / 'stack.yaml'
    path.write_text(CONFIG)
    return load_config(path)


@pytest.fixture
def make_node(ros_domain: int) -> Iterator[Any]:
    """A real rory_supervisor node whose context got these ROS arguments."""
    made: list[tuple[Node, Context]] = []

    def make(*ros_args: str) -> Node:
        context = Context()
        rclpy.init(args=['rory', '--ros-args', *own_ros_args(ros_args)], context=context,
                   domain_id=ros_domain, signal_handler_options=SignalHandlerOptions.NO)
        node = Node('rory_supervisor', context=context, start_parameter_services=False)
        made.append((node, context))
        return node

    yield make
    for node, context in made:
        node.destroy_node()
        context.try_shutdown()


def test_without_overrides_the_file_is_in_force_and_every_setting_is_declared(
    config: SupervisorConfig, make_node: Any
) -> None:
    node = make_node()
    assert apply_parameters(node, config) == config
    assert node.get_parameter('store').value == str(config.store)
    assert node.get_parameter('amcl.method').value == 'rory'
    assert node.get_parameter('amcl.checkpoint_interval').value == 2.0
    # Unset in the file: NOT_SET, the node's keyvars.yaml decides.
    assert node.get_parameter('navigator.checkpoint_interval').value is None
    assert node.get_parameter('navigator.hang_timeout').value == 0.0  # off
    assert node.get_parameter('amcl.max_restarts').value == 5
    for cfg in config.nodes:
        for setting in NODE_SETTINGS:
            assert node.has_parameter(f'{cfg.name}.{setting.name}')
            descriptor = node.describe_parameter(f'{cfg.name}.{setting.name}')
            assert descriptor.read_only and descriptor.description


def test_overrides_scoped_to_the_supervisor_change_only_what_they_name(
    config: SupervisorConfig, make_node: Any, tmp_path: Path
) -> None:
    node = make_node('-p', f'rory_supervisor:store:={tmp_path}/robot1',
                     '-p', 'rory_supervisor:amcl.method:=replay',
                     '-p', 'rory_supervisor:amcl.checkpoint_interval:=1',  # an int is fine
                     '-p', 'rory_supervisor:amcl.replay:=fast',
                     '-p', 'rory_supervisor:navigator.hang_timeout:=3.5',
                     '-p', 'rory_supervisor:navigator.start_timeout:=0',
                     '-p', 'rory_supervisor:navigator.warm_standby:=true',
                     '-p', 'rory_supervisor:navigator.max_restarts:=2',
                     '-p', 'other_node:amcl.method:=checkpoint')
    applied = apply_parameters(node, config)
    amcl, navigator = applied.nodes
    assert applied.store == tmp_path / 'robot1'
    assert amcl.method is Method.REPLAY and amcl.checkpoint_interval == 1.0
    assert amcl.replay is ReplayPace.FAST
    assert navigator.hang_timeout == 3.5 and navigator.start_timeout is None
    assert navigator.warm_standby is True and navigator.backoff.max_restarts == 2
    assert navigator.method is Method.RESTART and navigator.command == config.nodes[1].command
    assert applied.safe_state == config.safe_state and applied.dds == config.dds


def test_a_parameters_file_overrides_like_the_command_line(
    config: SupervisorConfig, make_node: Any, tmp_path: Path
) -> None:
    params = tmp_path / 'robot1.yaml'
    params.write_text('rory_supervisor:\n  ros__parameters:\n'
                      '    amcl: {replay: fast, warm_standby: false}\n'
                      '/**:\n  ros__parameters:\n    use_sim_time: false\n')
    amcl = apply_parameters(make_node('--params-file', str(params)), config).nodes[0]
    assert amcl.replay is ReplayPace.FAST and amcl.warm_standby is False


@pytest.mark.parametrize(('override', 'name', 'reason'), [
    ('amcl.method:=respawn', 'amcl.method', "must be one of rory, restart, checkpoint, replay"),
    ('amcl.replay:=slow', 'amcl.replay', 'must be one of paced, fast'),
    ('amcl.checkpoint_interval:=-1.0', 'amcl.checkpoint_interval', 'must be > 0'),
    ('amcl.checkpoint_interval:=often', 'amcl.checkpoint_interval', 'must be a number'),
    ('amcl.hang_timeout:=-2', 'amcl.hang_timeout', 'must be > 0'),
    ('amcl.warm_standby:=1', 'amcl.warm_standby', 'must be true or false'),
    ('amcl.max_restarts:=0', 'amcl.max_restarts', 'must be a positive integer'),
    ('amcl.methd:=restart', 'amcl.methd', 'unknown setting; known: method'),
])
def test_a_bad_override_is_refused_naming_the_parameter_and_the_node(
    override: str, name: str, reason: str, config: SupervisorConfig, make_node: Any
) -> None:
    node = make_node('-r', '__ns:=/robot1', '-p', f'rory_supervisor:{override}')
    with pytest.raises(ParameterError) as caught:
        apply_parameters(node, config)
    assert caught.value.name == name
    assert str(caught.value).startswith(f'parameter {name} of /robot1/rory_supervisor: ')
    assert reason in caught.value.reason


def test_parameters_are_read_only_once_declared(
    config: SupervisorConfig, make_node: Any
) -> None:
    node = make_node()
    apply_parameters(node, config)
    result = node.set_parameters([rclpy.parameter.Parameter('amcl.method', value='restart')])
    assert not result[0].successful
    assert node.get_parameter('amcl.method').value == 'rory'


def test_only_the_supervisors_own_scoped_overrides_lose_their_scope() -> None:
    given = ['-r', '__ns:=/robot1', '-p', 'rory_supervisor:store:=/s', '--param',
             'rory_supervisor:a.method:=restart', '-p', 'amcl:x:=1', '-p', 'y:=2',
             '-r', 'rory_supervisor:/a:=/b']
    assert own_ros_args(given) == ['-r', '__ns:=/robot1', '-p', 'store:=/s', '--param',
                                   'a.method:=restart', '-p', 'amcl:x:=1', '-p', 'y:=2',
                                   '-r', 'rory_supervisor:/a:=/b']


def test_in_a_parameters_file_the_supervisor_is_named_as_any_namespaced_node(
    config: SupervisorConfig, make_node: Any, tmp_path: Path
) -> None:
    params = tmp_path / 'robot1.yaml'
    params.write_text('/**/rory_supervisor:\n  ros__parameters:\n    amcl: {method: restart}\n')
    node = make_node('-r', '__ns:=/robot1', '--params-file', str(params))
    assert apply_parameters(node, config).nodes[0].method is Method.RESTART
