"""The standby program's parts that need no process: parsing, warm-up imports, activation."""

from __future__ import annotations

import os
import subprocess
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
        'from rory_runtime.node.attach import checkpointed\n'
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


# -- console scripts (an installed package's entry point) -----------------------------------


def _installed(tmp_path: Path, *, shebang: str = sys.executable) -> dict[str, str]:
    """A package `talker_pkg` with a console script `talker_node = talker_pkg.node:main`, as
    pip installs it: the module, its dist-info, and the script on PATH. The environment to
    run with."""
    site, bin_dir = tmp_path / 'site', tmp_path / 'bin'
    (site / 'talker_pkg').mkdir(parents=True)
    (site / 'talker_pkg' / '__init__.py').write_text('')
    (site / 'talker_pkg' / 'node.py').write_text(
        'import sys\n\ndef main():\n    print("talking", sys.argv[1:])\n    return 3\n')
    info = site / 'talker_pkg-1.0.dist-info'
    info.mkdir()
    (info / 'METADATA').write_text('Metadata-Version: 2.1\nName: talker-pkg\nVersion: 1.0\n')
    (info / 'entry_points.txt').write_text(
        '[console_scripts]\ntalker_node = talker_pkg.node:main\n')
    bin_dir.mkdir()
    script = bin_dir / 'talker_node'
    script.write_text(f'#!{shebang}\nimport sys\nfrom talker_pkg.node import main\n'
                      'sys.exit(main())\n')
    script.chmod(0o755)
    return {**os.environ, 'PYTHONPATH': str(site),
            'PATH': f'{bin_dir}{os.pathsep}{os.environ["PATH"]}'}


_RUN_FORKED = '''
import sys
from rory_runtime.standby import run_program
from rory_runtime.supervisor.zygote import forkable
program = forkable(sys.argv[1:])
print(program.module, program.entry, program.args, flush=True)
run_program(program)
'''


def test_a_console_script_runs_in_a_fork_as_its_wrapper_would(tmp_path: Path) -> None:
    env = _installed(tmp_path)
    done = subprocess.run([sys.executable, '-c', _RUN_FORKED, 'talker_node', 'a', '--ros-args'],
                          env=env, capture_output=True, text=True, timeout=60, check=False)
    assert done.stdout.splitlines() == [
        "talker_pkg.node main ('a', '--ros-args')", "talking ['a', '--ros-args']"], done.stderr
    assert done.returncode == 3  # what main returned, as sys.exit(main()) gives


def test_a_console_script_of_another_interpreter_is_not_forked(tmp_path: Path) -> None:
    env = _installed(tmp_path, shebang='/usr/bin/python3')
    done = subprocess.run(
        [sys.executable, '-c', 'import sys\nfrom rory_runtime.supervisor.zygote import forkable\n'
         'print(forkable(sys.argv[1:]))', 'talker_node'],
        env=env, capture_output=True, text=True, timeout=60, check=False)
    assert done.stdout.strip() == 'None', done.stderr


def test_this_installations_own_console_script_resolves_to_its_function(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from rory_runtime.supervisor.zygote import forkable

    monkeypatch.setenv('PATH', f'{Path(sys.executable).parent}{os.pathsep}{os.environ["PATH"]}')
    program = forkable(['rory-instrument', '--help'])
    assert program is not None
    assert (program.module, program.entry, program.args) == ('rory_instrument.cli', 'main',
                                                              ('--help',))
    assert program.argv == [str(Path(sys.executable).parent / 'rory-instrument'), '--help']
    assert forkable(['no-such-program-here']) is None
