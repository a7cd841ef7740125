"""How a node class gets its runtime (node/patching.py): nothing patched unsupervised; under the
supervisor the node's own entities go to its runtime and rclpy's own stay rclpy's. And the
node side's front door (node/attach.py) still exports what code written against it imports."""

from __future__ import annotations

from pathlib import Path

import pytest
from rclpy.context import Context
from rclpy.node import Node
from std_msgs.msg import Int64

from rory_runtime import protocol
from rory_runtime.node import attach, patching, runtime, state
from rory_runtime.protocol import Method, Mode


def test_unsupervised_nothing_is_patched(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv(protocol.ENV_NODE, raising=False)

    class Plain(Node):
        pass

    init, create_subscription = Plain.__init__, Plain.create_subscription
    node_init = Node.__init__
    assert patching.checkpointed(vars=('x',), manifest='sha256:0')(Plain) is Plain
    assert (Plain.__init__, Plain.create_subscription) == (init, create_subscription)
    patching.checkpoint_module(__name__, vars=('x',), manifest='sha256:0')
    assert Node.__init__ is node_init


def test_the_front_door_exports_what_earlier_code_imports() -> None:
    assert attach.checkpointed is patching.checkpointed
    assert attach.checkpoint_module is patching.checkpoint_module
    assert attach.NodeRuntime is runtime.NodeRuntime
    assert attach.RuntimeEnv is runtime.RuntimeEnv
    assert attach.CheckpointSpec is state.CheckpointSpec


@pytest.mark.ros
def test_a_decorated_node_gives_its_own_entities_to_its_runtime(
    context: Context, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    for name, value in ((protocol.ENV_NODE, 'counter'), (protocol.ENV_STORE, str(tmp_path)),
                        (protocol.ENV_INCARNATION, '1'), (protocol.ENV_METHOD, Method.RORY),
                        (protocol.ENV_MODE, Mode.FRESH)):
        monkeypatch.setenv(name, value)

    class Counter(Node):
        def __init__(self) -> None:
            super().__init__('counter', context=context)
            self.total = 0
            self.sub = self.create_subscription(Int64, '/numbers', self.on_number, 10)
            self.pub = self.create_publisher(Int64, '/total', 10)

        def on_number(self, msg: Int64) -> None:
            self.total += msg.data

    assert patching.checkpointed(vars=('total',), manifest='sha256:0')(Counter) is Counter
    node = Counter()
    try:
        rt = node.__dict__['_rory_runtime']
        assert isinstance(rt, runtime.NodeRuntime) and rt.node is node
        assert list(rt.router.inputs) == ['/numbers'] and node.sub.raw
        # rclpy's own /parameter_events and RORY's status publisher are not the node's outputs
        assert rt.gate.publishers == [node.pub]
    finally:
        rt.close()
        node.destroy_node()
