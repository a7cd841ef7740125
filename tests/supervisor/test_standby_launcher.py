"""WarmLauncher with real standby processes (rclpy, a DDS participant) and a small program."""

from __future__ import annotations

import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from rory_runtime.protocol import ENV_INCARNATION, ENV_MODE, ENV_QUARANTINE
from rory_runtime.supervisor.standby import WarmLauncher, standby_command

PROGRAM = '''
import json, os, sys
import rclpy
from rclpy.node import Node

def main():
    rclpy.init()
    node = Node('real_node')
    names = node.get_node_names()
    out = {
        'name': __name__, 'argv': sys.argv, 'path0': sys.path[0],
        'incarnation': os.environ.get('RORY_INCARNATION'),
        'mode': os.environ.get('RORY_MODE'), 'pid': os.getpid(),
        'nodes': names,
    }
    with open(sys.argv[1], 'w') as f:
        json.dump(out, f)
    node.destroy_node()
    rclpy.shutdown()
    return int(sys.argv[2])

if __name__ == '__main__':
    sys.exit(main())
'''


@pytest.fixture
def launcher() -> Iterator[WarmLauncher]:
    made = WarmLauncher()
    yield made
    made.close()


def _env(ros_domain: int, incarnation: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update({
        'ROS_DOMAIN_ID': str(ros_domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
        ENV_INCARNATION: str(incarnation), ENV_MODE: 'recover', ENV_QUARANTINE: '[]',
    })
    return env


def _wait_ready(launcher: WarmLauncher, argv: list[str], cwd: Path) -> None:
    standby = launcher.standby(argv, cwd)
    assert standby is not None
    deadline = time.monotonic() + 30
    while standby.ready_at is None:
        assert standby.proc.poll() is None, 'the standby died while warming up'
        assert time.monotonic() < deadline
        time.sleep(0.02)


def test_a_prepared_standby_becomes_the_program(
    tmp_path: Path, ros_domain: int, launcher: WarmLauncher
) -> None:
    (tmp_path / 'prog').mkdir()
    script = tmp_path / 'prog' / 'node.py'
    script.write_text(PROGRAM)
    out = tmp_path / 'out.json'
    argv = [sys.executable, str(script), str(out), '3']
    pid = launcher.prepare(argv, _env(ros_domain, 2), tmp_path)
    assert pid is not None
    _wait_ready(launcher, argv, tmp_path)
    child = launcher.spawn(argv, _env(ros_domain, 7), tmp_path)
    assert child.pid == pid and child.warm is True
    assert child.wait(timeout=30) == 3  # sys.exit(main()) as with python node.py
    seen = json.loads(out.read_text())
    assert seen['name'] == '__main__'
    assert seen['argv'] == [str(script), str(out), '3']
    assert seen['path0'] == str(script.parent)
    assert seen['incarnation'] == '7'  # the activation's, not the preparation's
    # The program's rclpy.init() was absorbed and its node replaced the placeholder.
    assert 'real_node' in seen['nodes']
    assert not [n for n in seen['nodes'] if n.startswith('_rory_standby_')]


def test_a_module_program_runs_as_python_dash_m_would(
    tmp_path: Path, ros_domain: int, launcher: WarmLauncher
) -> None:
    package = tmp_path / 'prog_pkg'
    package.mkdir()
    (package / '__init__.py').write_text('')
    (package / 'node.py').write_text(PROGRAM)
    out = tmp_path / 'out.json'
    argv = [sys.executable, '-m', 'prog_pkg.node', str(out), '0']
    launcher.prepare(argv, _env(ros_domain, 2), tmp_path)
    _wait_ready(launcher, argv, tmp_path)
    child = launcher.spawn(argv, _env(ros_domain, 3), tmp_path)
    assert child.warm is True
    assert child.wait(timeout=30) == 0
    seen = json.loads(out.read_text())
    assert seen['name'] == '__main__' and seen['incarnation'] == '3'
    assert seen['argv'] == [str(package / 'node.py'), str(out), '0']


def test_a_changed_environment_starts_cold_and_says_why(
    tmp_path: Path, ros_domain: int, launcher: WarmLauncher
) -> None:
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    argv = [sys.executable, str(script), str(tmp_path / 'out.json'), '0']
    standby_pid = launcher.prepare(argv, _env(ros_domain, 2), tmp_path)
    env = _env(ros_domain, 3)
    env['SOMETHING_ELSE'] = 'changed'
    child = launcher.spawn(argv, env, tmp_path)
    assert child.warm is False and child.pid != standby_pid
    assert 'SOMETHING_ELSE' in child.why_cold
    assert child.wait(timeout=60) == 0
    assert json.loads((tmp_path / 'out.json').read_text())['incarnation'] == '3'
    assert standby_pid is not None
    with pytest.raises(ChildProcessError):  # killed and reaped, not left behind
        os.waitpid(standby_pid, os.WNOHANG)


def test_a_dead_standby_is_not_used(
    tmp_path: Path, ros_domain: int, launcher: WarmLauncher
) -> None:
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    argv = [sys.executable, str(script), str(tmp_path / 'out.json'), '0']
    launcher.prepare(argv, _env(ros_domain, 2), tmp_path)
    standby = launcher.standby(argv, tmp_path)
    assert standby is not None
    standby.proc.kill()
    standby.proc.wait()
    child = launcher.spawn(argv, _env(ros_domain, 3), tmp_path)
    assert child.warm is False
    assert 'had exited' in child.why_cold
    assert child.wait(timeout=60) == 0


def test_close_ends_every_standby(tmp_path: Path, ros_domain: int, launcher: WarmLauncher) -> None:
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    argv = [sys.executable, str(script), 'x', '0']
    launcher.prepare(argv, _env(ros_domain, 2), tmp_path)
    standby = launcher.standby(argv, tmp_path)
    assert standby is not None
    launcher.close()
    assert standby.proc.poll() is not None
    assert launcher.standby(argv, tmp_path) is None


@pytest.mark.parametrize('argv', [
    ['/usr/bin/env', 'node'], ['python'], ['python', '-u', 'node.py'], ['python', '-c', 'x'],
])
def test_only_plain_python_programs_get_a_standby(argv: list[str]) -> None:
    assert standby_command(argv, control_fd=3, ready_fd=4) is None


def test_the_standby_command_keeps_the_programs_arguments() -> None:
    assert standby_command(['python3', '-m', 'pkg.node', '--ros-args'], control_fd=5,
                           ready_fd=6) == [
        'python3', '-m', 'rory_runtime.standby', '--control-fd', '5', '--ready-fd', '6', '--',
        '-m', 'pkg.node', '--ros-args',
    ]
