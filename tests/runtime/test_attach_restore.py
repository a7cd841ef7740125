"""Restore refuses a checkpoint of another code version and falls back to an older one."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from rory_runtime import codec
from rory_runtime.attach import NodeRuntime, RuntimeEnv
from rory_runtime.protocol import Method, Mode
from rory_runtime.state import CheckpointSpec
from rory_runtime.store import Checkpoint, CheckpointStore


class _Node:
    """The restored object: plain attributes, and a logger like rclpy's."""

    def __init__(self) -> None:
        self.total = 0

    def get_logger(self) -> Any:
        return logging.getLogger('test-node')


def _checkpoint(seq: int, manifest: str, total: int) -> Checkpoint:
    return Checkpoint(
        node='n', seq=seq, incarnation=1, created_ns=time.time_ns(), manifest=manifest,
        method='rory', cut=seq, windows={}, vars_blob=codec.encode_vars({'total': total}),
    )


def test_checkpoint_of_other_code_is_refused_and_the_older_one_restored(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path, 'n')
    store.write(_checkpoint(1, 'sha256:current', total=10))
    store.write(_checkpoint(2, 'sha256:older-code', total=99))
    env = RuntimeEnv('n', tmp_path, 2, Method.RORY, Mode.RECOVER, 2.0)
    runtime = NodeRuntime(CheckpointSpec(('total',), 'sha256:current'), env)
    runtime.node = _Node()  # type: ignore[assignment]
    refused: list[str] = []
    restored = runtime._restore(refused)
    assert restored is not None and restored['seq'] == 1
    assert runtime.node.total == 10  # type: ignore[attr-defined]
    assert len(refused) == 1 and 'different version of the instrumented code' in refused[0]
    # set aside, so it no longer counts as one of the two kept and is not tried again
    assert [p.name for p in store.paths()] == ['0000000001.ckpt']
    assert (store.dir / '0000000002.ckpt.refused').exists()
    runtime.close()


def test_no_valid_checkpoint_restores_nothing_and_says_why(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path, 'n')
    path = store.write(_checkpoint(1, 'sha256:current', total=10))
    data = bytearray(path.read_bytes())
    data[-1] ^= 0xFF  # corrupt the checksum
    path.write_bytes(bytes(data))
    env = RuntimeEnv('n', tmp_path, 2, Method.RORY, Mode.RECOVER, 2.0)
    runtime = NodeRuntime(CheckpointSpec(('total',), 'sha256:current'), env)
    runtime.node = _Node()  # type: ignore[assignment]
    refused: list[str] = []
    assert runtime._restore(refused) is None
    assert runtime.node.total == 0  # type: ignore[attr-defined]
    assert 'checksum' in refused[0]
    runtime.close()
