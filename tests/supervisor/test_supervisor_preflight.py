"""Before anything starts, `rory supervise` checks what a user gets wrong first: a program not
on PATH or a script not where nodes run, a store it cannot use, a YAML error (with its
line and column), relative file arguments; `rory --version`. Each is one line and exit 2."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path

import pytest

from rory_eval.harness.scenario import scenario_env
from rory_runtime.errors import ConfigError
from rory_runtime.supervisor.config import (
    SupervisorConfig,
    check_commands,
    check_store,
    load_config,
)
from rory_runtime.supervisor.embed import absolute_file_arguments


def _config(tmp_path: Path, text: str) -> Path:
    path = tmp_path / 'supervise.yaml'
    path.write_text(textwrap.dedent(text), encoding='utf-8')
    return path


def _refused(check: Callable[[SupervisorConfig], None], path: Path) -> ConfigError:
    with pytest.raises(ConfigError) as caught:
        check(load_config(path))
    return caught.value


def test_a_program_not_on_path_is_named_with_its_node(tmp_path: Path) -> None:
    err = _refused(check_commands, _config(tmp_path, '''
        nodes:
          - {name: integrator, command: [integrator_node_nowhere]}
    '''))
    assert err.field == 'nodes[0].command'
    assert err.reason == 'node integrator: integrator_node_nowhere is not on PATH'


def test_a_node_can_find_its_program_on_its_own_path(tmp_path: Path) -> None:
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    program = bin_dir / 'integrator_node'
    program.write_text('#!/bin/sh\n')
    program.chmod(program.stat().st_mode | stat.S_IXUSR)
    check_commands(load_config(_config(tmp_path, f'''
        nodes:
          - name: integrator
            command: [integrator_node]
            env: {{PATH: {bin_dir}}}
    ''')))


def test_a_script_not_where_nodes_run_is_named(tmp_path: Path) -> None:
    (tmp_path / 'out').mkdir()
    (tmp_path / 'out' / 'there.py').write_text('')
    check_commands(load_config(_config(tmp_path, '''
        nodes:
          - {name: a, command: [python, out/there.py]}
          - {name: b, command: [python, -m, some.module]}
          - {name: c, command: [python, -c, 'pass']}
    ''')))
    err = _refused(check_commands, _config(tmp_path, '''
        nodes:
          - {name: a, command: [python, out/there.py]}
          - {name: integrator, command: [python, out/nothere.py]}
    '''))
    assert err.field == 'nodes[1].command'
    assert err.reason == (f'node integrator: out/nothere.py: no such file (looked in '
                          f'{tmp_path}, where nodes run)')


def test_a_relative_program_must_be_an_executable_file(tmp_path: Path) -> None:
    (tmp_path / 'run.sh').write_text('#!/bin/sh\n')  # not executable
    err = _refused(check_commands, _config(tmp_path, '''
        nodes:
          - {name: a, command: [./run.sh]}
    '''))
    assert err.reason == f'node a: ./run.sh is not an executable file (looked in {tmp_path})'


@pytest.mark.parametrize('store', ['a_file', 'a_file/store'])
def test_a_store_on_a_file_is_refused_and_the_file_kept(tmp_path: Path, store: str) -> None:
    (tmp_path / 'a_file').write_text('data that must survive')
    err = _refused(check_store, _config(tmp_path, f'''
        store: {store}
        nodes:
          - {{name: a, command: [python, -c, 'pass']}}
    '''))
    assert err.field == 'store'
    assert err.reason == (f'{tmp_path / store}: cannot create or write: '
                          f'{tmp_path / "a_file"} is not a folder')
    assert (tmp_path / 'a_file').read_text() == 'data that must survive'


def test_checking_a_store_makes_nothing(tmp_path: Path) -> None:
    # A ROS parameter may still name another store: the file's is not made by the check.
    check_store(load_config(_config(tmp_path, '''
        store: deep/er/store
        nodes:
          - {name: a, command: [python, -c, 'pass']}
    ''')))
    assert not (tmp_path / 'deep').exists()


def test_a_yaml_error_says_file_line_and_column(tmp_path: Path) -> None:
    path = _config(tmp_path, 'nodes:\n  - name: a\n   command: [x]\n')
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    text = str(caught.value)
    assert text.startswith(f'{path}:3:4: not valid YAML: ')
    assert '\n' not in text and '<unicode string>' not in text


def test_relative_file_arguments_are_made_absolute_where_rory_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert absolute_file_arguments(
        ['-r', '__ns:=/r1', '--params-file', 'st/params.yaml', '-p', 'a:=1',
         '--log-config-file', '/etc/log.cfg', '--params-file']) == (
        '-r', '__ns:=/r1', '--params-file', str(tmp_path / 'st' / 'params.yaml'), '-p', 'a:=1',
        '--log-config-file', '/etc/log.cfg', '--params-file')


def _rory(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', 'rory_runtime.cli', *argv], cwd=cwd,
                          capture_output=True, text=True, timeout=60, check=False)


def test_the_command_line_says_one_line_and_exits_2(tmp_path: Path) -> None:
    _config(tmp_path, '''
        nodes:
          - {name: integrator, command: [integrator_node_nowhere]}
    ''')
    done = _rory('supervise', 'supervise.yaml', cwd=tmp_path)
    assert done.returncode == 2
    assert done.stderr == (f'rory: error: {tmp_path / "supervise.yaml"}: nodes[0].command: '
                           'node integrator: integrator_node_nowhere is not on PATH\n')
    assert not (tmp_path / '.rory').exists()  # nothing started, nothing made


@pytest.mark.ros
def test_a_store_that_cannot_be_made_ends_the_start_in_one_line(
    tmp_path: Path, ros_domain: int
) -> None:
    # /proc takes no folder, whoever asks: refused when the store is claimed, before any node.
    _config(tmp_path, '''
        store: /proc/rory-store
        nodes:
          - {name: a, command: [python, -c, 'import time; time.sleep(30)']}
    ''')
    done = subprocess.run([sys.executable, '-m', 'rory_runtime.cli', 'supervise',
                           'supervise.yaml'], cwd=tmp_path, env=scenario_env(ros_domain),
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 2, done.stdout + done.stderr
    assert done.stderr.startswith(f'rory: error: {tmp_path / "supervise.yaml"}: store: '
                                  '/proc/rory-store: cannot create or write: ')
    assert done.stderr.count('\n') == 1 and 'Traceback' not in done.stderr
    assert 'spawned' not in done.stdout


def test_version(tmp_path: Path) -> None:
    done = _rory('--version', cwd=tmp_path)
    assert done.returncode == 0
    assert done.stdout.startswith('rory ') and done.stdout.strip() != 'rory'


def test_a_package_and_its_executable_name_the_console_script(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # As `ros2 run rory-ros2 rory-instrument`: this installation's own distribution.
    monkeypatch.setenv('PATH', f'{Path(sys.executable).parent}{os.pathsep}{os.environ["PATH"]}')
    config = load_config(_config(tmp_path, '''
        nodes:
          - {name: a, command: [rory-ros2, rory-instrument, --help]}
          - {name: b, command: [rory-ros2, not-a-script]}
    '''))
    assert config.nodes[0].command == (str(Path(sys.executable).parent / 'rory-instrument'),
                                       '--help')
    assert config.nodes[1].command == ('rory-ros2', 'not-a-script')  # left for the check
    with pytest.raises(ConfigError, match='rory-ros2 is not on PATH'):
        check_commands(config)
