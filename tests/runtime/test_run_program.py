"""`rory sim` runs the simulator as a child (rory_runtime/cli.py, `_run_program`), so that the
runtime never imports it: the arguments, the exit code and the signals that reach `rory` pass
through, as if the child were the command itself."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import termios
import time

import pytest

CHILD = '''
import os, signal, sys, time
got = []
def note(signum, _frame):
    got.append(signum)
    print(f'child got {signal.Signals(signum).name}', flush=True)
for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
    signal.signal(sig, note)
print('child argv', sys.argv[1:], flush=True)
if sys.argv[2] == 'die':
    os.kill(os.getpid(), signal.SIGKILL)
if sys.argv[2] == 'wait':
    end = time.monotonic() + 60
    while not got and time.monotonic() < end:
        time.sleep(0.01)
    time.sleep(0.5)  # a second one, if it comes, is printed too
sys.exit(int(sys.argv[1]))
'''

PARENT = '''
import sys
from rory_runtime.cli import _run_program
print('parent says', _run_program([sys.executable, '-c', {child!r}, *sys.argv[1:]]), flush=True)
'''


def _start(*args: str) -> subprocess.Popen[str]:
    # Its own session, no terminal: as under a supervisor or a test harness.
    return subprocess.Popen([sys.executable, '-c', PARENT.format(child=CHILD), *args],
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, text=True,
                            start_new_session=True)


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


IN_A_TERMINAL = """
import fcntl, os, sys, termios
os.setsid()
fcntl.ioctl(0, termios.TIOCSCTTY, 0)  # the pseudo-terminal on 0, 1 and 2 becomes ours
os.execv(sys.executable, [sys.executable, *sys.argv[1:]])
"""


class Terminal:
    """rory (PARENT) in the foreground of a pseudo-terminal of its own, as typed in a shell."""

    def __init__(self, *args: str) -> None:
        self.controller, terminal = os.openpty()
        attrs = termios.tcgetattr(terminal)
        attrs[3] = (attrs[3] | termios.NOFLSH) & ~termios.ECHO  # keep output at Ctrl-C, no ^C
        termios.tcsetattr(terminal, termios.TCSANOW, attrs)
        self.parent = subprocess.Popen(
            [sys.executable, '-c', IN_A_TERMINAL, '-c', PARENT.format(child=CHILD), *args],
            stdin=terminal, stdout=terminal, stderr=terminal)
        os.close(terminal)
        self.seen = b''

    def wait_for(self, text: bytes) -> None:
        while text not in self.seen:
            self.seen += os.read(self.controller, 4096)

    def lines(self) -> list[str]:
        """Everything it printed, once every process of the terminal is gone."""
        while True:
            try:
                chunk = os.read(self.controller, 4096)
            except OSError:  # EIO: every process of the terminal has closed it
                break
            if not chunk:
                break
            self.seen += chunk
        os.close(self.controller)
        return [line.strip() for line in self.seen.decode().splitlines() if line.strip()]


def test_ctrl_c_in_a_terminal_reaches_the_child_and_rory_ends_with_its_code() -> None:
    terminal = Terminal('3', 'wait')
    terminal.wait_for(b"'wait']\r\n")
    os.write(terminal.controller, b'\x03')  # the terminal: SIGINT to rory and the child
    assert terminal.lines() == ["child argv ['3', 'wait']", 'child got SIGINT', 'parent says 3']
    assert terminal.parent.wait(timeout=60) == 0


def test_in_a_terminals_foreground_rory_passes_on_no_keyboard_signal() -> None:
    # The child had it from the terminal already; a SIGTERM still goes on.
    terminal = Terminal('3', 'wait')
    terminal.wait_for(b"'wait']\r\n")
    terminal.parent.send_signal(signal.SIGINT)
    time.sleep(0.3)
    terminal.parent.send_signal(signal.SIGTERM)
    assert terminal.lines() == ["child argv ['3', 'wait']", 'child got SIGTERM', 'parent says 3']
