"""The node's checkpoint tick: a snapshot on the executor, packed and written on the I/O thread,
its large arrays copied into the buffers of the checkpoint before (codec.ArrayPool).

Driven directly on a NodeRuntime whose node is a plain object holding the key variables; the
store is real, and the I/O thread is the runtime's own."""

from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np
from rcl_interfaces.msg import ListParametersResult
from rclpy.parameter import Parameter

from rory_runtime import codec
from rory_runtime.attach import CheckpointSpec, NodeRuntime, RuntimeEnv
from rory_runtime.protocol import Method, Mode


class _Node:
    """Key variables (a grid large enough to be pooled, a counter), rclpy's logger and no
    parameters."""

    def __init__(self) -> None:
        self.grid = np.zeros((256, 256), dtype=np.float32)  # 256 kB
        self.ticks = 0

    def get_logger(self) -> logging.Logger:
        return logging.getLogger('test-node')

    def list_parameters(self, _prefixes: list[str], _depth: int) -> ListParametersResult:
        return ListParametersResult()

    def get_parameters(self, _names: list[str]) -> list[Parameter]:
        return []


def _wait_for_io(rt: NodeRuntime) -> None:
    done = threading.Event()
    rt._io.submit(done.set)
    assert done.wait(10), 'the I/O thread did not finish its jobs'


def test_each_checkpoint_holds_its_instant_while_buffers_pass_from_one_to_the_next(
    tmp_path: Path,
) -> None:
    env = RuntimeEnv(node_id='n', store=tmp_path, incarnation=1, method=Method.CHECKPOINT,
                     mode=Mode.FRESH, interval=2.0)
    rt = NodeRuntime(CheckpointSpec(('grid', 'ticks'), 'sha256:0'), env)
    node = _Node()
    rt.node = node  # type: ignore[assignment]
    rt._next_seq = rt.checkpoints.next_seq()  # what start-up does
    try:
        rt._prime_array_pool()  # what release submits to the I/O thread
        assert len(rt._array_pool) == 1
        for tick in range(1, 4):
            node.grid[tick, tick] = float(tick)
            node.ticks = tick
            rt._checkpoint_tick()
            # The node changes its grid at once; the checkpoint must not see it.
            node.grid[tick, tick] = -1.0
            _wait_for_io(rt)
            assert len(rt._array_pool) == 1  # this checkpoint's buffer, for the next
            latest = rt.checkpoints.latest_valid()
            assert latest is not None and latest.seq == tick
            values = codec.decode_vars(latest.vars_blob)
            assert values['ticks'] == tick
            assert values['grid'][tick, tick] == float(tick)
            assert (values['grid'] == -1.0).sum() == tick - 1  # earlier ticks' changes only
            node.grid[tick, tick] = -1.0
    finally:
        rt.close()
