"""ForkLauncher with a real zygote, real standbys (rclpy, a DDS participant) and a small
program: what a node forked from the supervisor's fork server sees."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from rory_runtime.protocol import ENV_INCARNATION, ENV_MODE, ENV_QUARANTINE
from rory_runtime.supervisor.zygote import forkable, init_signature, node_level, ros_arguments

pytestmark = pytest.mark.ros

PROGRAM = '''
import json, os, sys, time
import rclpy
from rclpy.node import Node

def main():
    rclpy.init()
    node = Node('real_node')
    names = node.get_node_names()
    deadline = time.monotonic() + 10
    while os.environ.get('WAIT_FOR_NODE', 'real_node') not in names and time.monotonic() < deadline:
        time.sleep(0.05)
        names = node.get_node_names()
    out = {
        'name': __name__, 'argv': sys.argv, 'path0': sys.path[0],
        'incarnation': os.environ.get('RORY_INCARNATION'),
        'mode': os.environ.get('RORY_MODE'), 'pid': os.getpid(), 'ppid': os.getppid(),
        'cwd': os.getcwd(), 'nodes': names, 'sid': os.getsid(0),
        'threads': sorted(open(f'/proc/self/task/{t}/comm').read().strip()
                          for t in os.listdir('/proc/self/task')),
        'cmdline': open('/proc/self/cmdline', 'rb').read().split(b'\\0')[0].decode(),
    }
    with open(sys.argv[1], 'w') as f:
        json.dump(out, f)
    node.destroy_node()
    rclpy.shutdown()
    return int(sys.argv[2])

if __name__ == '__main__':
    sys.exit(main())
'''


class Host:
    """The launcher in its own fresh process (launcher_host.py)."""

    def __init__(self, domain: int, prefixed_output: Path | None = None) -> None:
        env = {**os.environ, 'ROS_DOMAIN_ID': str(domain),
               'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
        if prefixed_output is not None:
            env['LAUNCHER_HOST_PREFIXED_OUTPUT'] = str(prefixed_output)
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name('launcher_host.py'))], env=env,
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def ask(self, op: str, **fields: Any) -> dict[str, Any]:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(json.dumps({'op': op, **fields}) + '\n')
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        assert line, f'the launcher host ended ({self.proc.wait()})'
        return dict(json.loads(line))

    def close(self) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(OSError, AssertionError):
                self.ask('close')
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def launcher(ros_domain: int) -> Iterator[Host]:
    host = Host(ros_domain)
    try:
        yield host
    finally:
        host.close()


def _env(ros_domain: int, incarnation: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update({
        'ROS_DOMAIN_ID': str(ros_domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST',
        ENV_INCARNATION: str(incarnation), ENV_MODE: 'recover', ENV_QUARANTINE: '[]',
    })
    return env


def _wait_ready(launcher: Host, argv: list[str], cwd: Path) -> None:
    deadline = time.monotonic() + 30
    while True:
        standby = launcher.ask('standby', argv=argv, cwd=str(cwd))
        assert standby['pid'] is not None
        if standby['ready']:
            return
        assert standby['alive'], 'the standby died while warming up'
        assert time.monotonic() < deadline
        time.sleep(0.02)


def test_a_prepared_standby_becomes_the_program(
    tmp_path: Path, ros_domain: int, launcher: Host
) -> None:
    (tmp_path / 'prog').mkdir()
    script = tmp_path / 'prog' / 'node.py'
    script.write_text(PROGRAM)
    out = tmp_path / 'out.json'
    argv = [sys.executable, str(script), str(out), '3']
    pid = launcher.ask('prepare', argv=argv, env=_env(ros_domain, 2), cwd=str(tmp_path))['pid']
    assert pid is not None
    _wait_ready(launcher, argv, tmp_path)
    child = launcher.ask('spawn', argv=argv, env=_env(ros_domain, 7), cwd=str(tmp_path))
    assert child['pid'] == pid and child['warm'] is True
    # sys.exit(main()) as with python node.py
    assert launcher.ask('wait', pid=pid, timeout=30)['code'] == 3
    seen = json.loads(out.read_text())
    assert seen['name'] == '__main__'
    assert seen['argv'] == [str(script), str(out), '3']
    assert seen['path0'] == str(script.parent)
    assert seen['incarnation'] == '7'  # the activation's, not the preparation's
    # This process's child, in a session of its own, showing its own command line.
    assert seen['ppid'] == child['host'] and seen['sid'] == seen['pid']
    assert seen['cmdline'].endswith(f'{script} {out} 3')
    # The program's rclpy.init() was absorbed and its node replaced the placeholder.
    assert 'real_node' in seen['nodes']
    assert not [n for n in seen['nodes'] if n.startswith('_rory_standby_')]


def test_a_module_program_runs_as_python_dash_m_would(
    tmp_path: Path, ros_domain: int, launcher: Host
) -> None:
    package = tmp_path / 'prog_pkg'
    package.mkdir()
    (package / '__init__.py').write_text('')
    (package / 'node.py').write_text(PROGRAM)
    out = tmp_path / 'out.json'
    argv = [sys.executable, '-m', 'prog_pkg.node', str(out), '0']
    launcher.ask('prepare', argv=argv, env=_env(ros_domain, 2), cwd=str(tmp_path))
    _wait_ready(launcher, argv, tmp_path)
    child = launcher.ask('spawn', argv=argv, env=_env(ros_domain, 3), cwd=str(tmp_path))
    assert child['warm'] is True
    assert launcher.ask('wait', pid=child['pid'], timeout=30)['code'] == 0
    seen = json.loads(out.read_text())
    assert seen['name'] == '__main__' and seen['incarnation'] == '3'
    assert seen['argv'] == [str(package / 'node.py'), str(out), '0']


def test_another_init_forks_cold_and_keeps_the_standby_for_the_nodes_it_fits(
    tmp_path: Path, ros_domain: int, launcher: Host
) -> None:
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    argv = [sys.executable, str(script), str(tmp_path / 'out.json'), '0']
    standby = launcher.ask('prepare', argv=argv, env=_env(ros_domain, 2), cwd=str(tmp_path))
    # A log level is rclpy.init's alone (parameters and remaps a node's own arguments carry).
    other = [*argv, '--ros-args', '--log-level', 'warn']
    child = launcher.ask('spawn', argv=other, env=_env(ros_domain, 3), cwd=str(tmp_path))
    assert child['warm'] is False and child['pid'] != standby['pid']
    assert child['why_cold'] == 'no standby waiting'
    assert launcher.ask('wait', pid=child['pid'], timeout=60)['code'] == 0
    seen = json.loads((tmp_path / 'out.json').read_text())
    assert seen['incarnation'] == '3' and seen['ppid'] == child['host']
    assert launcher.ask('standby', argv=argv, cwd=str(tmp_path))['pid'] == standby['pid']


def test_one_standby_serves_every_node_with_the_same_init(
    tmp_path: Path, ros_domain: int, launcher: Host
) -> None:
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    first = [sys.executable, str(script), str(tmp_path / 'a.json'), '0']
    second = [sys.executable, str(script), str(tmp_path / 'b.json'), '0']
    pid = launcher.ask('prepare', argv=first, env=_env(ros_domain, 2), cwd=str(tmp_path))['pid']
    again = launcher.ask('prepare', argv=second, env=_env(ros_domain, 5), cwd=str(tmp_path))
    assert again['pid'] == pid
    _wait_ready(launcher, second, tmp_path)
    child = launcher.ask('spawn', argv=second, env=_env(ros_domain, 6), cwd=str(tmp_path))
    assert child['pid'] == pid and child['warm'] is True
    assert launcher.ask('wait', pid=pid, timeout=30)['code'] == 0
    assert json.loads((tmp_path / 'b.json').read_text())['incarnation'] == '6'
    # Used: the next start of either is cold until a new one is prepared.
    assert launcher.ask('standby', argv=first, cwd=str(tmp_path))['pid'] is None


def test_a_node_beyond_the_pool_starts_from_a_spare_fork(
    tmp_path: Path, ros_domain: int, launcher: Host
) -> None:
    # A pool of one, two nodes: the second struck at the same time starts from a fork made
    # before the crash, with no rclpy.init until it runs, as a cold fork would.
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    first = [sys.executable, str(script), str(tmp_path / 'a.json'), '0']
    second = [sys.executable, str(script), str(tmp_path / 'b.json'), '4']
    launcher.ask('prepare', argv=first, env=_env(ros_domain, 2), cwd=str(tmp_path))
    pool = launcher.ask('prepare', argv=second, env=_env(ros_domain, 2), cwd=str(tmp_path))
    assert len(pool['pool']) == 1 and len(pool['spares']) == 1
    _wait_ready(launcher, first, tmp_path)
    warm = launcher.ask('spawn', argv=first, env=_env(ros_domain, 3), cwd=str(tmp_path))
    cold = launcher.ask('spawn', argv=second, env=_env(ros_domain, 8), cwd=str(tmp_path))
    assert warm['warm'] is True and warm['pid'] == pool['pool'][0]
    assert cold['warm'] is False and cold['pid'] == pool['spares'][0]
    assert cold['why_cold'] == 'no standby waiting (the pool of 1 is in use); from a spare fork'
    assert launcher.ask('wait', pid=warm['pid'], timeout=30)['code'] == 0
    assert launcher.ask('wait', pid=cold['pid'], timeout=60)['code'] == 4
    seen = json.loads((tmp_path / 'b.json').read_text())
    assert seen['name'] == '__main__' and seen['incarnation'] == '8'
    assert seen['argv'] == [str(script), str(tmp_path / 'b.json'), '4']
    assert seen['ppid'] == cold['host'] and seen['sid'] == seen['pid']
    assert seen['cmdline'].endswith(f'{script} {tmp_path / "b.json"} 4')
    assert 'real_node' in seen['nodes']


def test_a_dead_standby_is_not_used(tmp_path: Path, ros_domain: int, launcher: Host) -> None:
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    argv = [sys.executable, str(script), str(tmp_path / 'out.json'), '0']
    launcher.ask('prepare', argv=argv, env=_env(ros_domain, 2), cwd=str(tmp_path))
    assert launcher.ask('kill_standby', argv=argv, cwd=str(tmp_path))['code'] == -signal.SIGKILL
    child = launcher.ask('spawn', argv=argv, env=_env(ros_domain, 3), cwd=str(tmp_path))
    assert child['warm'] is False and 'had exited' in child['why_cold']
    assert launcher.ask('wait', pid=child['pid'], timeout=60)['code'] == 0


def test_a_forked_node_has_none_of_the_supervisors_threads_or_participant(
    tmp_path: Path, ros_domain: int, launcher: Host
) -> None:
    # The host runs a participant and an executor thread, as the supervisor does, when the
    # node is forked: the node gets a participant of its own and only its own threads.
    launcher.ask('participant', name='supervisor_like')
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    argv = [sys.executable, str(script), str(tmp_path / 'out.json'), '0']
    env = {**_env(ros_domain, 1), 'WAIT_FOR_NODE': 'supervisor_like'}
    child = launcher.ask('spawn', argv=argv, env=env, cwd=str(tmp_path))
    assert launcher.ask('wait', pid=child['pid'], timeout=60)['code'] == 0
    seen = json.loads((tmp_path / 'out.json').read_text())
    # A participant of its own, which found the host's over DDS.
    assert {'real_node', 'supervisor_like'} <= set(seen['nodes'])
    assert 'rory-ros' not in seen['threads']


def test_close_ends_every_standby_and_the_zygote(
    tmp_path: Path, ros_domain: int, launcher: Host
) -> None:
    script = tmp_path / 'node.py'
    script.write_text(PROGRAM)
    argv = [sys.executable, str(script), 'x', '0']
    pid = launcher.ask('prepare', argv=argv, env=_env(ros_domain, 2), cwd=str(tmp_path))['pid']
    assert launcher.ask('close')['zygote_reaped'] is True
    launcher.proc.wait(timeout=20)
    assert not Path(f'/proc/{pid}').exists()  # the standby is gone, reaped


def test_a_command_that_is_not_a_python_program_is_started_with_exec(
    tmp_path: Path, launcher: Host
) -> None:
    argv = ['/bin/sh', '-c', 'exit 4']
    child = launcher.ask('spawn', argv=argv, env=dict(os.environ), cwd=str(tmp_path))
    assert child['warm'] is False and 'not a python' in child['why_cold']
    assert launcher.ask('wait', pid=child['pid'], timeout=10)['code'] == 4
    prepared = launcher.ask('prepare', argv=argv, env=dict(os.environ), cwd=str(tmp_path))
    assert prepared['pid'] is None


@pytest.mark.parametrize('argv', [
    ['/usr/bin/env', 'node'], ['python'], ['python', '-u', 'node.py'], ['python', '-c', 'x'],
])
def test_only_plain_python_programs_are_forked(argv: list[str]) -> None:
    assert forkable(argv) is None


def test_nodes_share_a_standby_when_their_ros_arguments_and_dds_environment_agree() -> None:
    program = forkable(['python', 'node.py', 'a', '--ros-args', '--log-level', 'warn', '--',
                        'b'])
    assert program is not None
    assert ros_arguments(program.args) == ('--log-level', 'warn')
    env = {'ROS_DOMAIN_ID': '3', 'RORY_NODE': 'a', 'HOME': '/h'}
    same = init_signature(program, env)
    assert init_signature(program, {**env, 'RORY_NODE': 'b', 'HOME': '/x'}) == same
    assert init_signature(program, {**env, 'ROS_DOMAIN_ID': '4'}) != same


def test_parameters_and_remaps_alone_share_the_standby_that_has_no_arguments() -> None:
    env = {'ROS_DOMAIN_ID': '3'}

    def signature(*ros_args: str) -> object:
        program = forkable(['python', 'node.py', '--ros-args', *ros_args])
        assert program is not None
        return init_signature(program, env)

    bare = forkable(['python', 'node.py'])
    assert bare is not None
    plain = init_signature(bare, env)
    assert signature('-p', 'x:=1', '-r', '__node:=b', '--params-file', '/p.yaml') == plain
    assert signature('--param', 'y:=2', '--remap', '/a:=/b') == plain
    assert node_level(('-p', 'x:=1', '-r', 'a:=b'))
    assert not node_level(('-p', 'x:=1', '--log-level', 'warn'))
    assert not node_level(('-p',))
    assert signature('-p', 'x:=1', '--enclave', '/e') != plain


NAMED = '''
import json, sys
import rclpy
from rclpy.node import Node

rclpy.init()
node = Node('real_node', cli_args=['--ros-args', '-p', 'own:=mine'])
node.declare_parameter('answer', 0)
node.declare_parameter('own', '')
other = Node('unremapped', use_global_arguments=False)
other.declare_parameter('answer', 0)
with open(sys.argv[1], 'w') as f:
    json.dump({'name': node.get_name(), 'answer': node.get_parameter('answer').value,
               'own': node.get_parameter('own').value,
               'other': [other.get_name(), other.get_parameter('answer').value]}, f)
rclpy.shutdown()
'''


def test_a_standby_without_arguments_gives_the_nodes_their_parameters_and_remaps(
    tmp_path: Path, ros_domain: int, launcher: Host
) -> None:
    script = tmp_path / 'named.py'
    script.write_text(NAMED)
    first = [sys.executable, str(script), str(tmp_path / 'a.json'), '--ros-args', '-p',
             'answer:=1']
    second = [sys.executable, str(script), str(tmp_path / 'b.json'), '--ros-args', '-p',
              'answer:=42', '-r', '__node:=renamed', '-p', 'own:=theirs']
    pid = launcher.ask('prepare', argv=first, env=_env(ros_domain, 2), cwd=str(tmp_path))['pid']
    assert launcher.ask('prepare', argv=second, env=_env(ros_domain, 2),
                        cwd=str(tmp_path))['pid'] == pid  # one standby for both
    _wait_ready(launcher, second, tmp_path)
    child = launcher.ask('spawn', argv=second, env=_env(ros_domain, 3), cwd=str(tmp_path))
    assert child['pid'] == pid and child['warm'] is True
    assert launcher.ask('wait', pid=pid, timeout=30)['code'] == 0
    seen = json.loads((tmp_path / 'b.json').read_text())
    # As rclpy.init(args) would have: the remap and the parameter reach the node; its own
    # cli_args win over them; a node that asked for no global arguments gets none.
    assert seen == {'name': 'renamed', 'answer': 42, 'own': 'mine',
                    'other': ['unremapped', 0]}


CHATTY = '''
import sys, time
print('to stdout from', sys.argv[1])
print('to stderr from', sys.argv[1], file=sys.stderr)
sys.stdout.write('no line end')
'''


def test_output_lines_carry_the_label_of_the_node_the_process_is(
    tmp_path: Path, ros_domain: int
) -> None:
    """Prefixed output (supervisor/output.py): a standby's lines carry the node it became; a
    cold fork and an exec'd command their own; a line cut by the exit is written whole."""
    script = tmp_path / 'chatty.py'
    script.write_text(CHATTY)
    host = Host(ros_domain, prefixed_output=tmp_path / 'console')
    try:
        warm = [sys.executable, str(script), 'alpha']
        host.ask('prepare', argv=warm, env=_env(ros_domain, 2), cwd=str(tmp_path))
        _wait_ready(host, warm, tmp_path)
        started = [host.ask('spawn', argv=warm, env=_env(ros_domain, 3), cwd=str(tmp_path),
                            label='alpha')]
        assert started[0]['warm'] is True
        started.append(host.ask('spawn', argv=[sys.executable, str(script), 'beta'],
                                env=_env(ros_domain, 3), cwd=str(tmp_path), label='beta'))
        assert started[1]['warm'] is False
        shell = 'echo to stdout from gamma; echo to stderr from gamma >&2'
        started.append(host.ask('spawn', argv=['bash', '-c', shell], env=_env(ros_domain, 3),
                                cwd=str(tmp_path), label='gamma'))
        for child in started:
            assert host.ask('wait', pid=child['pid'], timeout=30)['code'] == 0
    finally:
        host.close()  # closes the prefixer: what is left in the pipes is written
    out = (tmp_path / 'console.out').read_text().splitlines()
    err = (tmp_path / 'console.err').read_text().splitlines()
    for name in ('alpha', 'beta'):
        assert f'[{name}] to stdout from {name}' in out
        assert f'[{name}] no line end' in out
        assert f'[{name}] to stderr from {name}' in err
    assert '[gamma] to stdout from gamma' in out and '[gamma] to stderr from gamma' in err
    assert all(line.startswith(('[alpha] ', '[beta] ', '[gamma] ', '[rory-standby] '))
               for line in out + err), out + err
