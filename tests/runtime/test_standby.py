"""The standby program's parts that need no process: parsing, warm-up imports, activation."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from rory_runtime.standby import (
    Activation,
    Program,
    StandbyError,
    absorb_init,
    foreign_imports,
    read_activation,
    warm_imports,
)


def test_program_parses_a_script_and_a_module() -> None:
    script = Program.parse(['out/node.py', '--ros-args', '-p', 'a:=1'])
    assert script.script == Path('out/node.py') and script.module is None
    assert script.argv == ['out/node.py', '--ros-args', '-p', 'a:=1']
    module = Program.parse(['-m', 'pkg.node', 'x'])
    assert module.module == 'pkg.node' and module.args == ('x',)


@pytest.mark.parametrize('argv', [[], ['-u', 'node.py'], ['-c', 'print(1)'], ['-m']])
def test_program_refuses_what_it_cannot_run_warm(argv: list[str]) -> None:
    with pytest.raises(StandbyError, match='not a script or -m module'):
        Program.parse(argv)


def _program_tree(tmp_path: Path) -> Path:
    (tmp_path / 'node.py').write_text(
        'from __future__ import annotations\n'
        'import json\n'
        'import helper\n'
        'from std_msgs.msg import String, Bool\n'
        'def main():\n'
        '    import colorsys  # imports inside functions count too\n'
    )
    (tmp_path / 'helper.py').write_text('import fractions\nfrom . import nothing\n')
    return tmp_path / 'node.py'


def test_foreign_imports_follow_own_modules_but_never_take_them(tmp_path: Path) -> None:
    found = dict(foreign_imports(Program.parse([str(_program_tree(tmp_path))])))
    assert found == {
        'json': (), 'std_msgs.msg': ('String', 'Bool'), 'colorsys': (), 'fractions': (),
    }


def test_warm_imports_never_import_a_module_that_decorates_a_node(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A foreign package whose import decorates a node class: it must be imported only after
    # activation, when the environment that decides how it is decorated exists.
    pkg = tmp_path / 'site' / 'decorating_pkg'
    pkg.mkdir(parents=True)
    (pkg / '__init__.py').write_text(
        'from rory_runtime.attach import checkpointed\n'
        'from rclpy.node import Node\n'
        '@checkpointed(vars=("x",), manifest="m")\n'
        'class N(Node):\n'
        '    pass\n'
    )
    home = tmp_path / 'prog'
    home.mkdir()
    (home / 'node.py').write_text('import decorating_pkg\nimport textwrap\n')
    monkeypatch.syspath_prepend(str(tmp_path / 'site'))
    monkeypatch.setenv('RORY_NODE', 'n')
    failed = warm_imports(Program.parse([str(home / 'node.py')]))
    assert failed == ['decorating_pkg']
    assert 'decorating_pkg' not in sys.modules
    assert 'textwrap' in sys.modules


def test_activation_round_trip_and_end_of_file() -> None:
    r, w = os.pipe()
    activation = Activation(('python', 'n.py', 'x'), {'RORY_INCARNATION': '3'}, '/work')
    os.write(w, activation.encode())
    assert read_activation(r) == activation
    os.close(w)
    assert read_activation(r) is None
    os.close(r)


@pytest.mark.parametrize('line', [
    b'not json\n', b'{}\n',
    b'{"argv": ["p"], "env": [1], "cwd": "/"}\n',
    b'{"argv": ["p"], "env": {"a": 1}, "cwd": "/"}\n',
    b'{"argv": [], "env": {}, "cwd": "/"}\n',
    b'{"argv": ["p", 2], "env": {}, "cwd": "/"}\n',
    b'{"argv": ["p"], "env": {}, "cwd": 3}\n',
])
def test_a_bad_activation_is_refused(line: bytes) -> None:
    r, w = os.pipe()
    os.write(w, line)
    os.close(w)
    with pytest.raises(StandbyError, match='bad activation message'):
        read_activation(r)
    os.close(r)


class _FakeRclpy:
    """Only the calls absorb_init makes (unit test: no ROS here)."""

    def __init__(self) -> None:
        self.calls: list[tuple[Any, ...]] = []
        self.initialised = True
        self.init = self._init

    def _init(self, *args: Any, **kwargs: Any) -> None:
        self.calls.append(('init', args, kwargs))
        self.initialised = True

    def ok(self) -> bool:
        return self.initialised

    def try_shutdown(self) -> None:
        self.calls.append(('shutdown',))
        self.initialised = False


def test_the_programs_own_init_is_absorbed_when_it_asks_for_what_is_done(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    fake = _FakeRclpy()
    monkeypatch.setattr(sys, 'argv', ['node.py', '--ros-args', '-p', 'a:=1'])
    absorb_init(fake, ['node.py', '--ros-args', '-p', 'a:=1'])
    fake.init(args=None)
    assert fake.calls == []
    fake.init()  # a second call is the program's business: the real init answers it
    assert fake.calls == [('init', (), {})]


@pytest.mark.parametrize('call', [
    SimpleNamespace(args=(['node.py', '-other'],), kwargs={}),
    SimpleNamespace(args=(), kwargs={'domain_id': 7}),
])
def test_any_other_init_starts_cold(call: SimpleNamespace) -> None:
    fake = _FakeRclpy()
    absorb_init(fake, ['node.py'])
    fake.init(*call.args, **call.kwargs)
    assert fake.calls == [('shutdown',), ('init', call.args, call.kwargs)]
