"""A lifecycle node returns to its state through its own transition callbacks, and transitions
requested through ~/change_state are held until release, logged and replayed.

On real rclpy lifecycle nodes; requests are handed to the service's callback directly, as
the executor would.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from rory_runtime import protocol
from rory_runtime.log import read_segment
from rory_runtime.node import lifecycle as node_lifecycle
from rory_runtime.node.runtime import NodeRuntime, RuntimeEnv
from rory_runtime.node.state import CheckpointSpec
from rory_runtime.protocol import Method, Mode
from rory_runtime.supervisor.recovery import readings_first

pytestmark = pytest.mark.ros


class Camera(LifecycleNode):
    """Opens a buffer when configured, streams when active; refuses to activate when told."""

    def __init__(self, name: str, context: Context) -> None:
        super().__init__(name, context=context, start_parameter_services=False)
        self.calls: list[str] = []
        self.buffer: list[int] | None = None
        self.refuse_activation = False

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.calls.append('configure')
        self.buffer = []
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.calls.append('activate')
        if self.refuse_activation:
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self.calls.append('deactivate')
        return TransitionCallbackReturn.SUCCESS


def _runtime(tmp_path: Path, node: Camera, mode: Mode, incarnation: int) -> NodeRuntime:
    rt = NodeRuntime(CheckpointSpec(('buffer',), 'sha256:0'), RuntimeEnv(
        node_id='n', store=tmp_path, incarnation=incarnation, method=Method.RORY, mode=mode,
        interval=2.0))
    rt.node = node
    service = node_lifecycle.change_state_service(node)
    rt.adopt_service(service)
    return rt


def _change(node: Camera, label: str) -> bool:
    service = node_lifecycle.change_state_service(node)
    request = ChangeState.Request(transition=Transition(label=label))
    return bool(service.callback(request, ChangeState.Response()).success)


@pytest.mark.parametrize(('wanted', 'calls'), [
    ('active', ['configure', 'activate']),
    ('inactive', ['configure']),
    ('unconfigured', []),
])
def test_a_node_is_taken_back_to_its_state_through_its_callbacks(
    context: Context, wanted: str, calls: list[str],
) -> None:
    node = Camera('camera', context)
    assert node_lifecycle.restore(node, wanted) is None
    assert node_lifecycle.state_of(node) == wanted
    assert node.calls == calls
    assert (node.buffer is not None) == bool(calls)


def test_a_transition_the_node_refuses_is_named(context: Context) -> None:
    node = Camera('camera', context)
    node.refuse_activation = True
    error = node_lifecycle.restore(node, 'active')
    assert error is not None and 'activate returned FAILURE' in error
    assert 'the node is inactive' in error


def test_a_plain_node_has_no_lifecycle(context: Context) -> None:
    from rclpy.node import Node

    node = Node('plain', context=context, start_parameter_services=False)
    assert node_lifecycle.state_of(node) == ''
    assert node_lifecycle.restore(node, '') is None


def test_change_state_requests_are_held_logged_and_replayed(
    tmp_path: Path, context: Context,
) -> None:
    node = Camera('camera', context)
    rt = _runtime(tmp_path, node, Mode.FRESH, 1)
    executor = SingleThreadedExecutor(context=context)
    service = node_lifecycle.change_state_service(node)
    assert not executor.can_execute(service)  # a lifecycle manager waits until release
    rt.open_gates(next_segment=1)
    assert executor.can_execute(service)
    executor.shutdown()
    assert _change(node, 'configure') and _change(node, 'activate')
    assert _change(node, 'deactivate')
    rt.close()
    logged = list(read_segment(rt.checkpointer.segments.path(1)))
    assert [e.topic for e in logged] == [protocol.REQUEST_RECORD] * 3

    again = Camera('camera_2', context)
    rt2 = _runtime(tmp_path, again, Mode.RECOVER, 2)
    for entry in readings_first(logged):
        rt2.router.from_shadow(protocol.Msg(2, 0, entry.recv_ns, entry.source_ns, entry.seq,
                                            entry.topic, entry.data))
    assert again.calls == ['configure', 'activate', 'deactivate']
    assert node_lifecycle.state_of(again) == 'inactive'
