"""A node's parameters as state (in checkpoints, restored with its callbacks) and as input
(a change from outside logged and replayed; one a callback makes is not logged twice).

On real rclpy nodes (their parameter machinery is what is tested), without parameter
services; the runtime's delivery methods are driven directly.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from rcl_interfaces.msg import SetParametersResult
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter

from rory_runtime import protocol
from rory_runtime.log import read_segment
from rory_runtime.node import parameters as node_parameters
from rory_runtime.node.runtime import NodeRuntime, RuntimeEnv
from rory_runtime.node.state import CheckpointSpec
from rory_runtime.protocol import Method, Mode
from rory_runtime.supervisor.recovery import readings_first

pytestmark = pytest.mark.ros


class Tuned(Node):
    """A controller whose gain comes from a parameter, copied by its callbacks."""

    def __init__(self, context: Context) -> None:
        super().__init__('tuned', context=context, start_parameter_services=False)
        self.declare_parameter('gain', 1.0)
        self.declare_parameter('mode', 'slow')
        self.kp = 1.0
        self.seen: list[str] = []
        self.add_on_set_parameters_callback(self.on_set)
        self.add_post_set_parameters_callback(self.after_set)

    def on_set(self, params: list[Parameter]) -> SetParametersResult:
        self.seen += [f'on {p.name}={p.value}' for p in params]
        return SetParametersResult(successful=all(p.value != -1.0 for p in params))

    def after_set(self, params: list[Parameter]) -> None:
        for p in params:
            if p.name == 'gain':
                self.kp = p.value
        self.seen += [f'post {p.name}' for p in params]


def _runtime(tmp_path: Path, node: Node, mode: Mode, incarnation: int) -> NodeRuntime:
    env = RuntimeEnv(node_id='n', store=tmp_path, incarnation=incarnation, method=Method.RORY,
                     mode=mode, interval=2.0)
    rt = NodeRuntime(CheckpointSpec(('kp',), 'sha256:0'), env)
    rt.node = node
    rt.gate.watch_parameters(node)
    return rt


def test_a_checkpoints_parameters_are_restored_through_the_nodes_callbacks(
    context: Context,
) -> None:
    before = Tuned(context)
    before.set_parameters([Parameter('gain', value=2.5)])
    saved = node_parameters.snapshot(before)
    after = Tuned(context)
    restored, refused = node_parameters.restore(after, saved)
    assert restored == ['gain']  # mode did not change: not set again
    assert after.get_parameter('gain').value == 2.5 and after.kp == 2.5
    assert after.seen == ['on gain=2.5', 'post gain']
    assert refused == []


def test_a_parameter_the_new_process_does_not_declare_is_named_not_restored(
    context: Context,
) -> None:
    saved = node_parameters.pack([Parameter('gone', value=3)])
    restored, refused = node_parameters.restore(Tuned(context), saved)
    assert restored == []
    assert len(refused) == 1 and refused[0].startswith('parameter gone: not restored:')


def test_a_change_from_outside_is_logged_and_replays_with_its_callbacks(
    context: Context, tmp_path: Path,
) -> None:
    node = Tuned(context)
    rt = _runtime(tmp_path, node, Mode.FRESH, 1)
    early = node.set_parameters_atomically([Parameter('gain', value=9.0)])
    assert not early.successful and 'recovering' in early.reason  # isolated until release
    rt.open_gates(next_segment=1)
    assert node.set_parameters_atomically([Parameter('gain', value=3.0)]).successful
    assert node.kp == 3.0
    rt.close()
    logged = list(read_segment(rt.checkpointer.segments.path(1)))
    # (and the clock reading rclpy takes to stamp its /parameter_events message)
    assert [e.topic for e in logged] == [protocol.PARAMETERS_RECORD, protocol.CLOCK_RECORD]
    assert rt.applier.stats['parameter_changes'] == 1

    fresh = Tuned(context)
    rt2 = _runtime(tmp_path, fresh, Mode.RECOVER, 2)
    for entry in readings_first(logged):
        rt2.router.from_shadow(protocol.Msg(2, 0, entry.recv_ns, entry.source_ns, entry.seq,
                                            entry.topic, entry.data))
    assert fresh.get_parameter('gain').value == 3.0 and fresh.kp == 3.0
    assert fresh.seen == ['on gain=3.0', 'post gain']
    assert rt2.applier.stats['parameter_changes_replayed'] == 1


def test_a_change_a_callback_makes_is_not_logged_as_an_input(
    context: Context, tmp_path: Path,
) -> None:
    node = Tuned(context)
    rt = _runtime(tmp_path, node, Mode.FRESH, 1)
    rt.open_gates(next_segment=1)
    assert rt.applier.clock is not None
    rt.applier.clock.begin_live()  # inside an event, as a message callback would be
    try:
        node.set_parameters_atomically([Parameter('mode', value='fast')])
    finally:
        rt.applier.clock.end()
    assert node.get_parameter('mode').value == 'fast'
    assert rt.applier.stats['parameter_changes'] == 0
    rt.close()
    segments = rt.checkpointer.segments
    logged = [e.topic for n in segments.numbers() for e in read_segment(segments.path(n))]
    assert protocol.PARAMETERS_RECORD not in logged


def test_the_parameter_setting_services_wait_for_release(
    context: Context, tmp_path: Path,
) -> None:
    from rcl_interfaces.srv import GetParameters, SetParameters, SetParametersAtomically
    from rclpy.executors import SingleThreadedExecutor

    node = Node('served', context=context)  # with rclpy's parameter services
    rt = _runtime(tmp_path, node, Mode.RECOVER, 2)
    executor = SingleThreadedExecutor(context=context)
    by_type = {srv.srv_type: srv for srv in node.services}
    setting = [by_type[SetParameters], by_type[SetParametersAtomically]]
    assert not any(executor.can_execute(srv) for srv in setting)
    assert executor.can_execute(by_type[GetParameters])  # reading waits for nothing
    rt.open_gates(next_segment=1)
    assert all(executor.can_execute(srv) for srv in setting)
    executor.shutdown()
