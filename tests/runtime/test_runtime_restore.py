"""Restore refuses a checkpoint of another code version and falls back to an older one; and it
applies freshness rules (freshness.py): a stale variable is reset, kept or refuses the start."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

from rclpy.clock import ROSClock
from rclpy.time import Time

from rory_runtime import codec
from rory_runtime.freshness import Rule
from rory_runtime.node.runtime import NodeRuntime, RuntimeEnv
from rory_runtime.node.state import CheckpointSpec
from rory_runtime.protocol import Method, Mode, RestoredCheckpoint
from rory_runtime.store import Checkpoint, CheckpointStore


class _Node:
    """The restored object: plain attributes, a logger and a ROS clock like rclpy's."""

    def __init__(self, sim_now_s: float | None = None) -> None:
        self.total = 0
        self.pose = 'initial pose'
        self.clock = ROSClock()
        if sim_now_s is not None:  # what rclpy's TimeSource does under use_sim_time
            self.clock._set_ros_time_is_active(True)
            self.clock.set_ros_time_override(Time(nanoseconds=int(sim_now_s * 1e9)))

    class _Context:
        def ok(self) -> bool:
            return True

    context = _Context()

    def get_logger(self) -> Any:
        return logging.getLogger('test-node')

    def get_clock(self) -> ROSClock:
        return self.clock


def _checkpoint(seq: int, manifest: str, total: int) -> Checkpoint:
    return Checkpoint(
        node='n', seq=seq, incarnation=1, created_ns=time.time_ns(), manifest=manifest,
        method='rory', cut=seq, windows={}, vars_blob=codec.encode_vars({'total': total}),
    )


def _aged(tmp_path: Path, age_s: float, *, sim_taken_s: float | None = None) -> None:
    """One checkpoint of total and pose, taken age_s ago on the system clock (or at
    sim_taken_s of simulation time)."""
    clock_ns = (int(sim_taken_s * 1e9) if sim_taken_s is not None
                else time.time_ns() - int(age_s * 1e9))
    CheckpointStore(tmp_path, 'n').write(Checkpoint(
        node='n', seq=1, incarnation=1, created_ns=time.time_ns() - int(age_s * 1e9),
        manifest='sha256:m', method='rory', cut=1, windows={},
        vars_blob=codec.encode_vars({'total': 10, 'pose': 'saved pose'}),
        clock_ns=clock_ns, sim_time=sim_taken_s is not None))


def _restore(tmp_path: Path, on_stale: str, node: _Node | None = None,
             max_age: float = 5.0) -> tuple[_Node, RestoredCheckpoint | None]:
    env = RuntimeEnv('n', tmp_path, 2, Method.RORY, Mode.RECOVER, 2.0)
    spec = CheckpointSpec(('total', 'pose'), 'sha256:m',
                          freshness=(Rule('pose', max_age, on_stale),))
    runtime = NodeRuntime(spec, env)
    runtime.node = node or _Node()  # type: ignore[assignment]
    try:
        return runtime.node, runtime.restore([])  # type: ignore[return-value]
    finally:
        runtime.close()


def test_a_fresh_checkpoint_restores_every_variable(tmp_path: Path) -> None:
    _aged(tmp_path, 1.0)
    node, restored = _restore(tmp_path, 'reset')
    assert (node.total, node.pose) == (10, 'saved pose')
    assert restored is not None
    verdict = restored.freshness
    assert verdict.restored == ['total', 'pose'] and verdict.reset == []
    assert verdict.clock == 'system' and 1.0 <= verdict.age_s < 3.0
    assert verdict.max_age == {'pose': 5.0}


def test_a_stale_variable_is_reset_and_the_rest_restored(tmp_path: Path) -> None:
    _aged(tmp_path, 30.0)
    node, restored = _restore(tmp_path, 'reset')
    assert (node.total, node.pose) == (10, 'initial pose')  # __init__'s value stays
    assert restored is not None
    assert restored.freshness.restored == ['total']
    assert restored.freshness.reset == ['pose']


def test_a_stale_variable_under_keep_is_restored_and_reported(tmp_path: Path) -> None:
    _aged(tmp_path, 30.0)
    node, restored = _restore(tmp_path, 'keep')
    assert (node.total, node.pose) == (10, 'saved pose')
    assert restored is not None and restored.freshness.kept_stale == ['pose']


def test_a_stale_variable_under_refuse_restores_nothing(tmp_path: Path) -> None:
    _aged(tmp_path, 30.0)
    node, restored = _restore(tmp_path, 'refuse')
    assert (node.total, node.pose) == (0, 'initial pose')
    assert restored is not None and restored.freshness.refused == ['pose']


def test_under_sim_time_the_age_is_simulation_time(tmp_path: Path) -> None:
    # Taken at 100 s of simulation time, an hour of wall time ago: 3 s old in the simulation.
    _aged(tmp_path, 3600.0, sim_taken_s=100.0)
    node, restored = _restore(tmp_path, 'reset', _Node(sim_now_s=103.0))
    assert node.pose == 'saved pose'
    assert restored is not None and restored.freshness.clock == 'sim'
    assert abs(restored.freshness.age_s - 3.0) < 1e-6
    _, restored = _restore(tmp_path, 'reset', _Node(sim_now_s=110.0))
    assert restored is not None and restored.freshness.reset == ['pose']


def test_an_age_that_cannot_be_known_is_stale(tmp_path: Path) -> None:
    # A simulation restarted from zero: its clock is behind the checkpoint's.
    _aged(tmp_path, 1.0, sim_taken_s=100.0)
    node, restored = _restore(tmp_path, 'reset', _Node(sim_now_s=2.0))
    assert node.pose == 'initial pose'
    assert restored is not None and restored.freshness.age_s is None
    # Taken on the system clock, judged under simulation time.
    (tmp_path / 'n').rename(tmp_path / 'old')
    _aged(tmp_path, 1.0)
    node, restored = _restore(tmp_path, 'reset', _Node(sim_now_s=50.0))
    assert node.pose == 'initial pose'


def test_checkpoint_of_other_code_is_refused_and_the_older_one_restored(tmp_path: Path) -> None:
    store = CheckpointStore(tmp_path, 'n')
    store.write(_checkpoint(1, 'sha256:current', total=10))
    store.write(_checkpoint(2, 'sha256:older-code', total=99))
    env = RuntimeEnv('n', tmp_path, 2, Method.RORY, Mode.RECOVER, 2.0)
    runtime = NodeRuntime(CheckpointSpec(('total',), 'sha256:current'), env)
    runtime.node = _Node()  # type: ignore[assignment]
    refused: list[str] = []
    restored = runtime.restore(refused)
    assert restored is not None and restored.seq == 1
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
    assert runtime.restore(refused) is None
    assert runtime.node.total == 0  # type: ignore[attr-defined]
    assert 'checksum' in refused[0]
    runtime.close()
