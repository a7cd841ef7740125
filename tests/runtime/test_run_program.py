"""`rory sim` runs the simulator as a child (rory_runtime/cli.py, `_run_program`), so that the
runtime never imports it: the arguments, the exit code and the signals that reach `rory` pass
through, as if the child were the command itself."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

CHILD = '''
import os, signal, sys, time
def stop(signum, _frame):
    print(f'child got {signal.Signals(signum).name}', flush=True)
    sys.exit(int(sys.argv[1]))
signal.signal(signal.SIGTERM, stop)
signal.signal(signal.SIGINT, stop)
signal.signal(signal.SIGHUP, stop)
print('child argv', sys.argv[1:], flush=True)
if sys.argv[2] == 'die':
    os.kill(os.getpid(), signal.SIGKILL)
if sys.argv[2] == 'exit':
    sys.exit(int(sys.argv[1]))
time.sleep(60)
'''

PARENT = '''
import sys
from rory_runtime.cli import _run_program
print('parent says', _run_program([sys.executable, '-c', {child!r}, *sys.argv[1:]]), flush=True)
'''


def _start(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, '-c', PARENT.format(child=CHILD), *args],
                            stdout=subprocess.PIPE, text=True)


def test_arguments_and_exit_code_pass_through() -> None:
    parent = _start('5', 'exit', '--ros-args', '-r', '__ns:=/a b')
    out, _ = parent.communicate(timeout=60)
    assert out.splitlines() == ["child argv ['5', 'exit', '--ros-args', '-r', '__ns:=/a b']",
                                'parent says 5']
    assert parent.returncode == 0  # what the parent did with the code (printed it), not the child


@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_to_rory_reaches_the_child(sig: signal.Signals) -> None:
    # Sent to the parent alone (as `kill` does; Ctrl-C reaches the whole process group).
    parent = _start('3', 'wait')
    assert parent.stdout is not None
    assert parent.stdout.readline().startswith('child argv')
    parent.send_signal(sig)
    out, _ = parent.communicate(timeout=60)
    assert out.splitlines() == [f'child got {sig.name}', 'parent says 3']


def test_a_child_killed_by_a_signal_ends_rory_with_the_same_signal() -> None:
    parent = _start('0', 'die')
    out, _ = parent.communicate(timeout=60)
    assert parent.returncode == -signal.SIGKILL
    assert 'parent says' not in out


def test_ctrl_c_reaches_the_child_and_rory_ends_with_its_code() -> None:
    # Ctrl-C sends SIGINT to the terminal's foreground process group: rory and the child both.
    parent = subprocess.Popen([sys.executable, '-c', PARENT.format(child=CHILD), '3', 'wait'],
                              stdout=subprocess.PIPE, text=True, start_new_session=True)
    assert parent.stdout is not None
    assert parent.stdout.readline().startswith('child argv')
    os.killpg(parent.pid, signal.SIGINT)
    out, _ = parent.communicate(timeout=60)
    lines = out.splitlines()
    # Once from the terminal, maybe once more from rory (the simulator stops on the first).
    assert lines[-1] == 'parent says 3' and set(lines[:-1]) == {'child got SIGINT'}
