"""rory kill signals the node's current process, found from the store, and nothing else: not
a process that ended, not a pid the kernel gave to another process, not without a supervisor."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from rory_runtime.kill import main


@pytest.fixture
def child() -> Iterator[subprocess.Popen[bytes]]:
    """A process of this test's, standing for a node the supervisor (this process) spawned."""
    proc = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'])
    yield proc
    proc.kill()
    proc.wait()


def _store(tmp_path: Path, events: list[dict[str, object]], supervisor: int) -> Path:
    store = tmp_path / '.rory'
    store.mkdir()
    (store / 'supervisor.lock').write_text(f'{supervisor}\n')
    (store / 'events.jsonl').write_text(''.join(json.dumps(e) + '\n' for e in events))
    return store


def _spawn(pid: int, incarnation: int, node: str = 'integrator') -> dict[str, object]:
    return {'kind': 'spawn', 'node': node, 'pid': pid, 'incarnation': incarnation}


def test_the_node_current_process_gets_the_signal(
    tmp_path: Path, child: subprocess.Popen[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    store = _store(tmp_path, [
        _spawn(1, 1), {'kind': 'exit', 'node': 'integrator', 'incarnation': 1},
        _spawn(child.pid, 2), _spawn(2, 1, node='other'),
    ], os.getpid())
    assert main([str(store), 'integrator', '--signal', 'segv']) == 0
    assert child.wait(timeout=10) == -signal.SIGSEGV
    assert capsys.readouterr().out == (
        f'sent SIGSEGV to integrator (pid {child.pid}, incarnation 2)\n')


def test_a_node_whose_process_ended_is_not_signalled(
    tmp_path: Path, child: subprocess.Popen[bytes], capsys: pytest.CaptureFixture[str]
) -> None:
    store = _store(tmp_path, [
        _spawn(child.pid, 3), {'kind': 'exit', 'node': 'integrator', 'incarnation': 3},
    ], os.getpid())
    assert main([str(store), 'integrator']) == 2
    assert child.poll() is None
    assert capsys.readouterr().err == (f'rory kill: error: integrator is not running (its last '
                                       f'process, pid {child.pid}, has ended)\n')


def test_a_pid_that_is_not_the_supervisors_child_is_not_signalled(
    tmp_path: Path, child: subprocess.Popen[bytes],
) -> None:
    # The supervisor recorded this pid, but the process now holding it is not its child.
    store = _store(tmp_path, [_spawn(child.pid, 1)], os.getppid())
    assert main([str(store), 'integrator']) == 2
    assert child.poll() is None


@pytest.mark.parametrize(('lock', 'events', 'message'), [
    (None, [], 'no supervisor has run here'),
    ('999999999', [], 'no supervisor runs on this store now'),
    ('self', [], "no node 'integrator' was started here"),
])
def test_nothing_to_signal_is_said_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], lock: str | None,
    events: list[dict[str, object]], message: str,
) -> None:
    store = tmp_path / '.rory'
    store.mkdir()
    if lock is not None:
        (store / 'supervisor.lock').write_text(str(os.getpid()) if lock == 'self' else lock)
    (store / 'events.jsonl').write_text('')
    assert main([str(store), 'integrator']) == 2
    err = capsys.readouterr().err
    assert err.startswith('rory kill: error: ') and message in err and err.count('\n') == 1


def test_an_unknown_signal_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([str(tmp_path), 'integrator', '--signal', 'NOPE']) == 2
    assert capsys.readouterr().err == "rory kill: error: --signal: no signal 'NOPE'\n"
