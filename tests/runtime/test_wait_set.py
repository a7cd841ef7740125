"""Nothing of RORY's in the node's executor (issue 36; docs/architecture.md, "Nothing in the
node's executor"): in steady state, under every method, the executor of an instrumented node
waits on exactly the entities the original program made, by count and kind.

Real rclpy and DDS: the same node class is spun bare and under its runtime in an executor whose
wait sets are recorded as rclpy builds them (``_rclpy.WaitSet``'s sizes: subscriptions, guard
conditions, timers, clients, services, events). The runtime is released as the supervisor
releases it (methods that log wait for RELEASE on the shadow topic, sent here by a test
publisher outside the executor), then runs through its first checkpoints.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import rclpy.executors
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_msgs.msg import Int64, UInt8MultiArray
from std_srvs.srv import Trigger

from rory_runtime import protocol
from rory_runtime.node import patching
from rory_runtime.node.runtime import NodeRuntime
from rory_runtime.protocol import Method, Mode

pytestmark = pytest.mark.ros

Shape = tuple[int, int, int, int, int, int]
SECRET = b'k' * 32


class _RecordingRclpy:
    """rclpy's C module as the executor sees it, with each WaitSet's sizes kept."""

    def __init__(self, real: Any) -> None:
        self._real = real
        self.shapes: list[Shape] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self._real, name)

    def WaitSet(self, *args: Any) -> Any:
        self.shapes.append(tuple(args[:6]))  # type: ignore[arg-type]
        return self._real.WaitSet(*args)


@pytest.fixture
def recorded(monkeypatch: pytest.MonkeyPatch) -> Iterator[_RecordingRclpy]:
    recorder = _RecordingRclpy(rclpy.executors._rclpy)
    monkeypatch.setattr(rclpy.executors, '_rclpy', recorder)
    yield recorder


def _talker_class(context: Context) -> type[Node]:
    """A node as users write them: an input, an output, a timer, a service."""

    class Talker(Node):
        def __init__(self) -> None:
            super().__init__('talker', context=context)
            self.total = 0
            self.create_subscription(Int64, '/wait_set_numbers', self.on_number, 10)
            self.pub = self.create_publisher(Int64, '/wait_set_total', 10)
            self.create_timer(0.05, self.on_tick)
            self.create_service(Trigger, '/wait_set_reset', self.on_reset)

        def on_number(self, msg: Int64) -> None:
            self.total += msg.data

        def on_tick(self) -> None:
            self.pub.publish(Int64(data=self.total))

        def on_reset(self, _request: Any, response: Any) -> Any:
            self.total = 0
            response.success = True
            return response

    return Talker


def _steady_shapes(node: Node, executor: SingleThreadedExecutor, recorder: _RecordingRclpy,
                   seconds: float) -> set[Shape]:
    """The wait sets the executor built over ``seconds`` of spinning."""
    recorder.shapes.clear()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.05)
    return set(recorder.shapes)


def _spin_until(executor: SingleThreadedExecutor, done: Any, timeout: float = 10.0) -> None:
    end = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < end, 'timed out'
        executor.spin_once(timeout_sec=0.05)


@pytest.mark.parametrize('method', list(Method))
def test_the_executor_waits_on_the_original_entities_only(
    method: Method, context: Context, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    recorded: _RecordingRclpy,
) -> None:
    monkeypatch.delenv(protocol.ENV_NODE, raising=False)
    bare = _talker_class(context)()
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(bare)
    try:
        bare_shapes = _steady_shapes(bare, executor, recorded, 1.0)
    finally:
        executor.remove_node(bare)
        bare.destroy_node()
    assert len(bare_shapes) == 1, bare_shapes

    for name, value in ((protocol.ENV_NODE, 'talker'), (protocol.ENV_STORE, str(tmp_path)),
                        (protocol.ENV_INCARNATION, '1'), (protocol.ENV_METHOD, method.value),
                        (protocol.ENV_MODE, Mode.FRESH.value), (protocol.ENV_INTERVAL, '0.2'),
                        (protocol.ENV_SECRET, SECRET.hex())):
        monkeypatch.setenv(name, value)
    cls = patching.checkpointed(vars=('total',), manifest='sha256:0')(_talker_class(context))
    node = cls()
    runtime: NodeRuntime = node.__dict__['_rory_runtime']
    helper = Node('wait_set_supervisor', context=context)  # outside the executor
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        _spin_until(executor, lambda: runtime._hello_sent)
        if method.logs:
            # The supervisor's RELEASE, on the shadow topic, until the node has it.
            writer = helper.create_publisher(
                UInt8MultiArray, protocol.replay_topic('talker', 1), protocol.REPLAY_QOS)
            signed = protocol.SignedPublisher(writer, SECRET)
            end = time.monotonic() + 10.0
            while not runtime.released:
                assert time.monotonic() < end, 'never released'
                signed.publish(protocol.pack_release(1, 1, 0))
                for _ in range(4):
                    executor.spin_once(timeout_sec=0.05)
        _spin_until(executor, lambda: runtime.released and runtime.shadow_subscription is None)
        if method.checkpoints:
            checkpoints = runtime.checkpointer.checkpoints
            _spin_until(executor, lambda: checkpoints.latest_valid() is not None)
        shapes = _steady_shapes(node, executor, recorded, 1.0)
    finally:
        executor.remove_node(node)
        runtime.close()
        node.destroy_node()
        helper.destroy_node()
    assert shapes == bare_shapes
