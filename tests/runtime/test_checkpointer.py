"""The node's checkpoint tick (node/checkpointer.py): a snapshot on the executor, packed and
written on the I/O thread, its large arrays copied into the buffers of the checkpoint before
(codec.ArrayPool).

Driven directly on a NodeRuntime whose node is a plain object holding the key variables; the
store is real, and the I/O thread is the runtime's own."""

from __future__ import annotations

import errno
import logging
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from rcl_interfaces.msg import ListParametersResult
from rclpy.clock import Clock
from rclpy.clock_type import ClockType
from rclpy.parameter import Parameter

from rory_runtime import chunk_file, chunks, codec
from rory_runtime.node.runtime import NodeRuntime, RuntimeEnv
from rory_runtime.node.state import CheckpointSpec
from rory_runtime.protocol import CheckpointFailure, ErrorStatus, Method, Mode, Status


class _Node:
    """Key variables (a grid large enough to be pooled, a counter), rclpy's logger and
    clock, and no parameters."""

    def __init__(self) -> None:
        self.grid = np.zeros((256, 256), dtype=np.float32)  # 256 kB
        self.ticks = 0

    def get_clock(self) -> Clock:
        return Clock(clock_type=ClockType.ROS_TIME)

    def get_logger(self) -> logging.Logger:
        return logging.getLogger('test-node')

    def list_parameters(self, _prefixes: list[str], _depth: int) -> ListParametersResult:
        return ListParametersResult()

    def get_parameters(self, _names: list[str]) -> list[Parameter]:
        return []


def _wait_for_io(rt: NodeRuntime) -> None:
    done = threading.Event()
    rt.checkpointer.io.submit(done.set)
    assert done.wait(10), 'the I/O thread did not finish its jobs'


def test_each_checkpoint_holds_its_instant_while_buffers_pass_from_one_to_the_next(
    tmp_path: Path,
) -> None:
    env = RuntimeEnv(node_id='n', store=tmp_path, incarnation=1, method=Method.CHECKPOINT,
                     mode=Mode.FRESH, interval=2.0)
    rt = NodeRuntime(CheckpointSpec(('grid', 'ticks'), 'sha256:0'), env)
    node = _Node()
    rt.node = node  # type: ignore[assignment]
    rt.checkpointer.number_from_store()  # what start-up does
    try:
        # what release submits to the I/O thread
        rt.checkpointer.prime_array_pool(node)  # type: ignore[arg-type]
        assert len(rt.checkpointer.array_pool) == 1
        for tick in range(1, 4):
            node.grid[tick, tick] = float(tick)
            node.ticks = tick
            rt.checkpoint_tick()
            # The node changes its grid at once; the checkpoint must not see it.
            node.grid[tick, tick] = -1.0
            _wait_for_io(rt)
            assert len(rt.checkpointer.array_pool) == 1  # this checkpoint's buffer, for the next
            latest = rt.checkpointer.checkpoints.latest_valid()
            assert latest is not None and latest.seq == tick
            values = codec.decode_vars(latest.vars_blob)
            assert values['ticks'] == tick
            assert values['grid'][tick, tick] == float(tick)
            assert (values['grid'] == -1.0).sum() == tick - 1  # earlier ticks' changes only
            node.grid[tick, tick] = -1.0
    finally:
        rt.close()


def test_a_checkpoint_writes_only_the_chunks_its_snapshot_found_changed(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    written: list[int] = []
    real = chunk_file._pwrite_all

    def count(fd: int, data: bytes | memoryview, offset: int) -> None:
        written.append(len(data))
        real(fd, data, offset)

    monkeypatch.setattr(chunk_file, '_pwrite_all', count)
    env = RuntimeEnv(node_id='n', store=tmp_path, incarnation=1, method=Method.CHECKPOINT,
                     mode=Mode.FRESH, interval=2.0)
    rt = NodeRuntime(CheckpointSpec(('grid', 'ticks'), 'sha256:0'), env)
    node = _Node()
    node.grid = np.zeros((1024, 256), dtype=np.float32)  # 1 MiB: 8 chunks (all equal)
    rt.node = node  # type: ignore[assignment]
    rt.checkpointer.number_from_store()
    rows = chunks.CHUNK_BYTES // (256 * 4)
    try:
        for tick in range(4):
            written.clear()
            node.grid[tick * rows, 0] = float(tick + 1)  # a chunk of its own each time
            rt.checkpoint_tick()
            _wait_for_io(rt)
            latest = rt.checkpointer.checkpoints.latest_valid()
            assert latest is not None and latest.seq == tick + 1
            assert codec.decode_vars(latest.vars_blob)['grid'].tobytes() == node.grid.tobytes()
            # The first writes the changed chunk and the zeros once; then the changed one.
            assert written == [chunks.CHUNK_BYTES] * (2 if tick == 0 else 1)
    finally:
        rt.close()


def _released(tmp_path: Path, node: _Node) -> NodeRuntime:
    env = RuntimeEnv(node_id='n', store=tmp_path, incarnation=1, method=Method.CHECKPOINT,
                     mode=Mode.FRESH, interval=2.0)
    rt = NodeRuntime(CheckpointSpec(('ticks',), 'sha256:0'), env)
    rt.node = node  # type: ignore[assignment]
    rt.checkpointer.number_from_store()
    return rt


def test_a_clean_exit_takes_a_last_checkpoint_of_the_state_now(tmp_path: Path) -> None:
    node = _Node()
    rt = _released(tmp_path, node)
    rt.close()  # not released yet: nothing to keep
    assert rt.checkpointer.checkpoints.latest_valid() is None
    rt.open_gates(next_segment=1)
    node.ticks = 41
    rt.close()
    latest = rt.checkpointer.checkpoints.latest_valid()
    assert latest is not None and codec.decode_vars(latest.vars_blob)['ticks'] == 41
    rt.close()  # once
    assert rt.checkpointer.checkpoints.latest_valid() == latest


def test_after_a_callback_raised_no_checkpoint_is_taken_at_exit(tmp_path: Path) -> None:
    from dataclasses import dataclass, field

    from rclpy.qos import QoSProfile
    from rclpy.serialization import serialize_message
    from std_msgs.msg import Int64

    node = _Node()
    rt = _released(tmp_path, node)

    def half_applied(msg: Int64) -> None:
        node.ticks = -1  # the state is half-way through this message
        raise ValueError('bad message')

    @dataclass
    class _Sub:
        topic_name: str = '/x'
        callback: object = half_applied
        msg_type: type = Int64
        raw: bool = False
        qos_profile: QoSProfile = field(default_factory=lambda: QoSProfile(depth=10))

    sub = _Sub()
    rt.adopt_subscription(sub)  # type: ignore[arg-type]
    rt.open_gates(next_segment=1)
    info = {'source_timestamp': 1, 'received_timestamp': 1, 'publication_sequence_number': 1,
            'reception_sequence_number': None}
    with pytest.raises(ValueError, match='bad message'):
        sub.callback(bytes(serialize_message(Int64(data=1))), info)  # type: ignore[operator]
    rt.close()
    assert rt.checkpointer.checkpoints.latest_valid() is None


def test_a_checkpoint_not_taken_is_an_error_status_that_says_so_and_why(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The supervisor reads ``checkpoint`` (ErrorStatus.checkpoint_failed), not the message."""
    node = _Node()
    node.context = SimpleNamespace(ok=lambda: True)  # type: ignore[attr-defined]  # rclpy's
    rt = _released(tmp_path, node)
    sent: list[Status] = []
    rt.reporter.status = sent.append  # type: ignore[method-assign]
    try:
        del node.ticks  # a key variable that cannot be read: the snapshot is refused
        rt.checkpoint_tick()
        _wait_for_io(rt)
        node.ticks = 3

        def full(*_: object, **__: object) -> None:
            raise OSError(errno.ENOSPC, 'No space left on device')

        # the snapshot is taken, not written
        monkeypatch.setattr(rt.checkpointer.checkpoints, 'write', full)
        rt.checkpoint_tick()
        _wait_for_io(rt)
        rt.reporter.error('cannot log a message of /scan: disk full')  # an error of another kind
    finally:
        rt.close()
    errors = [s for s in sent if isinstance(s, ErrorStatus)]
    assert [(e.checkpoint, e.checkpoint_failed) for e in errors[:3]] == [
        (CheckpointFailure.SKIPPED, True), (CheckpointFailure.NOT_WRITTEN, True), (None, False)]
    assert errors[0].message.startswith("checkpoint skipped: variable 'ticks'")
    assert errors[1].message == 'checkpoint 1 not written: [Errno 28] No space left on device'
