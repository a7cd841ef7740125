"""A node's service servers as inputs: held until release, each request logged before its
handler runs, replayed with no response sent.

On real rclpy nodes and services (what the executor sees is what is tested); requests are
handed to the service's callback directly, as the executor would.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import SetBool

from rory_runtime import protocol
from rory_runtime.errors import RoryError
from rory_runtime.log import read_segment
from rory_runtime.node.runtime import NodeRuntime, RuntimeEnv
from rory_runtime.node.state import CheckpointSpec
from rory_runtime.protocol import Method, Mode
from rory_runtime.supervisor.recovery import readings_first

pytestmark = pytest.mark.ros


class Switch:
    """A handler that keeps what it was asked, and answers with how often."""

    def __init__(self) -> None:
        self.asked: list[bool] = []

    def __call__(self, request: Any, response: Any) -> Any:
        self.asked.append(request.data)
        response.success = True
        response.message = f'{len(self.asked)}'
        return response


def _served(tmp_path: Path, context: Context, mode: Mode, incarnation: int) -> tuple[
        NodeRuntime, Any, Switch]:
    node = Node(f'switch_{incarnation}', context=context, start_parameter_services=False)
    rt = NodeRuntime(CheckpointSpec(('x',), 'sha256:0'), RuntimeEnv(
        node_id='n', store=tmp_path, incarnation=incarnation, method=Method.RORY, mode=mode,
        interval=2.0))
    rt.node = node
    handler = Switch()
    srv = node.create_service(SetBool, '/switch', handler)
    rt.adopt_service(srv)
    return rt, srv, handler


def test_a_service_is_out_of_the_executors_wait_set_until_release(
    tmp_path: Path, context: Context,
) -> None:
    rt, srv, _ = _served(tmp_path, context, Mode.FRESH, 1)
    executor = SingleThreadedExecutor(context=context)
    assert not executor.can_execute(srv)  # a request waits in the service's queue
    rt.open_gates(next_segment=1)
    assert executor.can_execute(srv)
    executor.shutdown()


def test_requests_are_logged_and_replay_in_order_without_a_response(
    tmp_path: Path, context: Context,
) -> None:
    rt, srv, handler = _served(tmp_path, context, Mode.FRESH, 1)
    rt.open_gates(next_segment=1)
    for wanted in (True, False, True):
        response = srv.callback(SetBool.Request(data=wanted), SetBool.Response())
        assert response.success
    assert response.message == '3'
    rt.close()
    logged = list(read_segment(rt.checkpointer.segments.path(1)))
    assert [(e.topic, e.seq) for e in logged] == [(protocol.REQUEST_RECORD, 0)] * 3
    assert rt.applier.stats['requests'] == 3

    rt2, _, handler2 = _served(tmp_path, context, Mode.RECOVER, 2)
    for entry in readings_first(logged):
        rt2.router.from_shadow(protocol.Msg(2, 0, entry.recv_ns, entry.source_ns, entry.seq,
                                            entry.topic, entry.data))
    assert handler2.asked == handler.asked == [True, False, True]
    assert rt2.applier.stats['requests_replayed'] == 3


def test_an_async_service_handler_is_refused_by_name(tmp_path: Path, context: Context) -> None:
    node = Node('async_switch', context=context, start_parameter_services=False)
    rt = NodeRuntime(CheckpointSpec(('x',), 'sha256:0'), RuntimeEnv(
        node_id='n', store=tmp_path, incarnation=1, method=Method.RORY, mode=Mode.FRESH,
        interval=2.0))

    async def handler(request: Any, response: Any) -> Any:
        return response

    srv = node.create_service(SetBool, '/async_switch', handler)
    with pytest.raises(RoryError, match=r'async service callbacks.*/async_switch'):
        rt.adopt_service(srv)
