"""Reading and restoring key variables by path, on the node and in its module's globals."""

from __future__ import annotations

import re
import sys
import types
from collections.abc import Iterator

import pytest

from rory_runtime.errors import CodecError
from rory_runtime.node.state import CheckpointSpec, read_state, write_state


class Pid:
    def __init__(self) -> None:
        self.accu_e = 0.0
        self.last_e = 0.0


class Node:
    def __init__(self) -> None:
        self.total = 0
        self.pid = Pid()


@pytest.fixture
def module() -> Iterator[types.ModuleType]:
    mod = types.ModuleType('rorytest_state_module')
    mod.counter = 3  # type: ignore[attr-defined]
    mod.state = types.SimpleNamespace(pose=(1.0, 2.0))  # type: ignore[attr-defined]
    sys.modules[mod.__name__] = mod
    yield mod
    del sys.modules[mod.__name__]


def test_paths_and_module_globals_are_read_under_their_keys(module: types.ModuleType) -> None:
    spec = CheckpointSpec(
        ('total', 'pid.accu_e'), 'm', ('counter', 'state.pose'), module.__name__
    )
    node = Node()
    node.pid.accu_e = 1.5
    assert read_state(spec, node) == {
        'total': 0,
        'pid.accu_e': 1.5,
        'global:counter': 3,
        'global:state.pose': (1.0, 2.0),
    }


def test_restore_puts_each_value_inside_the_restored_objects(module: types.ModuleType) -> None:
    spec = CheckpointSpec(('total', 'pid.accu_e'), 'm', ('counter', 'state.pose'), module.__name__)
    node = Node()
    pid = node.pid
    write_state(
        spec,
        node,
        {'total': 7, 'pid.accu_e': 2.5, 'global:counter': 9, 'global:state.pose': (0.0, 1.0)},
    )
    assert node.total == 7
    assert node.pid is pid and pid.accu_e == 2.5  # set inside, not replaced
    assert module.counter == 9
    assert module.state.pose == (0.0, 1.0)


def test_missing_attribute_is_named(module: types.ModuleType) -> None:
    spec = CheckpointSpec(('pid.integral',), 'm')
    message = "variable 'pid.integral' is not set: no 'pid.integral'"
    with pytest.raises(CodecError, match=re.escape(message)):
        read_state(spec, Node())
    spec = CheckpointSpec((), 'm', ('nothing',), module.__name__)
    with pytest.raises(CodecError, match="module variable 'nothing' is not set"):
        read_state(spec, Node())


def test_restore_refuses_a_checkpoint_with_other_variables() -> None:
    spec = CheckpointSpec(('total',), 'm')
    with pytest.raises(CodecError, match='holds variables'):
        write_state(spec, Node(), {'total': 1, 'extra': 2})


def test_module_not_loaded_is_refused() -> None:
    spec = CheckpointSpec((), 'm', ('x',), 'rorytest_not_loaded')
    with pytest.raises(CodecError, match='not loaded'):
        read_state(spec, Node())
