"""A real `rory supervise` takes its settings as ROS parameters and shows them to ROS tools."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import rclpy
from rcl_interfaces.srv import GetParameters
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python
from rclpy.signals import SignalHandlerOptions
from supervision import events, stop, wait_for

from rory_eval.harness.scenario import prepare, scenario_env

pytestmark = pytest.mark.ros


def _get_parameters(domain: int, service: str, names: list[str]) -> list[object]:
    """What `ros2 param get` would print, through the node's own parameter service."""
    context = Context()
    rclpy.init(context=context, domain_id=domain, signal_handler_options=SignalHandlerOptions.NO)
    node = Node('param_reader', context=context)
    try:
        client = node.create_client(GetParameters, service)
        assert client.wait_for_service(timeout_sec=20), f'{service} never appeared'
        future = client.call_async(GetParameters.Request(names=names))
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        executor.spin_until_future_complete(future, timeout_sec=10)
        response = future.result()
        assert response is not None, f'{service} did not answer'
        return [parameter_value_to_python(v) for v in response.values]
    finally:
        node.destroy_node()  # its participant outlives a shut-down context otherwise
        context.try_shutdown()


def test_overrides_from_ros_args_take_effect_in_a_namespace_and_ros_tools_see_them(
    tmp_path: Path, ros_domain: int
) -> None:
    config = prepare(tmp_path, 'rory', interval=0.5, pace='paced')
    store = tmp_path / 'robot1-store'
    sup = subprocess.Popen(
        [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config),
         '--ros-args', '-r', '__ns:=/robot1',
         '-p', f'rory_supervisor:store:={store}',
         '-p', 'rory_supervisor:integrator.replay:=fast',
         '-p', 'rory_supervisor:integrator.warm_standby:=false'],
        env=scenario_env(ros_domain), cwd=tmp_path, stdout=subprocess.DEVNULL,
        stderr=subprocess.STDOUT, start_new_session=True)
    try:
        wait_for(lambda: any(e['kind'] == 'state' and e['new'] == 'RUNNING'
                             for e in events(store)), 30, 'the node running, in the new store')
        assert not (tmp_path / 'store-rory').exists(), "the file's store was not used"
        values = _get_parameters(ros_domain, '/robot1/rory_supervisor/get_parameters',
                                 ['store', 'integrator.replay', 'integrator.warm_standby',
                                  'integrator.checkpoint_interval', 'integrator.method'])
        assert values == [str(store), 'fast', False, 0.5, 'rory']
        # warm_standby false: no standby process was ever prepared.
        assert not [e for e in events(store) if e['kind'] == 'standby']
    finally:
        stop(sup)


def test_a_bad_override_exits_2_naming_the_parameter_and_touches_no_store(
    tmp_path: Path, ros_domain: int
) -> None:
    config = prepare(tmp_path, 'rory', interval=0.5, pace='paced')
    proc = subprocess.run(
        [sys.executable, '-m', 'rory_runtime.cli', 'supervise', str(config),
         '--ros-args', '-p', 'rory_supervisor:integrator.method:=respawn'],
        env=scenario_env(ros_domain), cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2, proc.stderr
    assert ('parameter integrator.method of /rory_supervisor: must be one of rory, restart, '
            "checkpoint, replay, got 'respawn'") in proc.stderr
    assert not (tmp_path / 'store-rory').exists()
