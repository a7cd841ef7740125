"""Warm standbys, the supervisor's side: one waiting process per node, used at its next start.

:class:`WarmLauncher` is a :class:`~.process.Launcher`. ``prepare()`` starts a standby
(``rory_runtime/standby.py``) for a node command while the node runs; ``spawn()`` for the same
command, folder and environment activates it instead of starting a cold process, and falls
back to a cold start (saying why) when there is none, it has died, or the environment differs
in anything but the keys a new incarnation changes.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..protocol import ENV_INCARNATION, ENV_MODE, ENV_QUARANTINE
from ..standby import encode_activation
from .process import PopenLauncher, _die_with_supervisor, _PopenChild
from .states import LOG_PREFIX

_logger = logging.getLogger('rory.supervisor')

ACTIVATION_KEYS = frozenset({ENV_INCARNATION, ENV_MODE, ENV_QUARANTINE})
"""Environment a standby receives at activation; everything else must match at preparation."""

_PYTHONS = frozenset({'python', 'python3', 'python3.11'})


def standby_command(argv: Sequence[str], *, control_fd: int, ready_fd: int) -> list[str] | None:
    """The standby's command line for a node's, or None when the node is not a plain Python
    program (``python node.py ...`` or ``python -m package.node ...``)."""
    if len(argv) < 2:
        return None
    if argv[0] != sys.executable and Path(argv[0]).name not in _PYTHONS:
        return None
    rest = list(argv[1:])
    if rest[0] == '-m' and len(rest) >= 2:
        pass
    elif rest[0].startswith('-'):
        return None  # interpreter options (-u, -X, -c): run those cold
    return [argv[0], '-m', 'rory_runtime.standby', '--control-fd', str(control_fd),
            '--ready-fd', str(ready_fd), '--', *rest]


def _key(argv: Sequence[str], cwd: Path) -> tuple[tuple[str, ...], str]:
    return tuple(argv), str(cwd)


def _fixed(env: Mapping[str, str]) -> dict[str, str]:
    return {k: v for k, v in env.items() if k not in ACTIVATION_KEYS}


@dataclass
class Standby:
    """One waiting process."""

    proc: subprocess.Popen[bytes]
    control: int  # write end of its control pipe
    env: dict[str, str]  # without the activation keys
    started: float
    ready_at: float | None = None
    done: threading.Event = field(default_factory=threading.Event)

    def drop(self) -> None:
        """Kill it and reap it (it holds nothing)."""
        with contextlib.suppress(OSError):
            os.close(self.control)
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=5.0)


class WarmChild(_PopenChild):
    """A node process, and whether it started from a standby."""

    def __init__(self, proc: subprocess.Popen[bytes], *, warm: bool, why_cold: str = '') -> None:
        super().__init__(proc)
        self.warm = warm
        self.why_cold = why_cold


class WarmLauncher(PopenLauncher):
    """Starts nodes from a standby when one is waiting, else cold.

    Args:
        clock: Monotonic clock.
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._standbys: dict[tuple[tuple[str, ...], str], Standby] = {}
        self._lock = threading.Lock()

    def prepare(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path) -> int | None:
        """Start a standby for the next ``spawn(argv, ...)``; its pid, or None when this node
        cannot have one. Replaces an earlier standby of the same command. Main thread only
        (PR_SET_PDEATHSIG follows the thread that forked)."""
        key = _key(argv, cwd)
        self.discard(argv, cwd)
        control_r, control_w = os.pipe()
        ready_r, ready_w = os.pipe()
        command = standby_command(argv, control_fd=control_r, ready_fd=ready_w)
        if command is None:
            for fd in (control_r, control_w, ready_r, ready_w):
                os.close(fd)
            return None
        os.set_inheritable(control_r, True)
        os.set_inheritable(ready_w, True)
        try:
            proc = subprocess.Popen(
                command, env=dict(env), cwd=cwd, start_new_session=True,
                preexec_fn=_die_with_supervisor, pass_fds=(control_r, ready_w),
            )
        except OSError:
            for fd in (control_r, control_w, ready_r, ready_w):
                os.close(fd)
            raise
        finally:
            with contextlib.suppress(OSError):
                os.close(control_r)
            with contextlib.suppress(OSError):
                os.close(ready_w)
        standby = Standby(proc, control_w, _fixed(env), self._clock())
        with self._lock:
            self._standbys[key] = standby

        def watch_ready() -> None:
            try:
                got = os.read(ready_r, 1)
            except OSError:
                got = b''
            finally:
                os.close(ready_r)
            if got:
                standby.ready_at = self._clock()
                _logger.info('%s standby pid %d ready in %.0f ms', LOG_PREFIX, proc.pid,
                             (standby.ready_at - standby.started) * 1000)
            elif not standby.done.is_set():
                _logger.warning('%s standby pid %d ended before it was ready (%s)', LOG_PREFIX,
                                proc.pid, proc.poll())

        threading.Thread(target=watch_ready, name='rory-standby', daemon=True).start()
        return proc.pid

    def standby(self, argv: Sequence[str], cwd: Path) -> Standby | None:
        """The standby waiting for this command, if any."""
        with self._lock:
            return self._standbys.get(_key(argv, cwd))

    def spawn(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path) -> WarmChild:
        """Activate the command's standby if it fits, else start cold."""
        with self._lock:
            standby = self._standbys.pop(_key(argv, cwd), None)
        why = 'no standby'
        if standby is not None:
            standby.done.set()
            code = standby.proc.poll()
            if code is not None:
                why = f'the standby had exited ({code})'
            elif standby.env != _fixed(env):
                changed = sorted(set(standby.env.items()) ^ set(_fixed(env).items()))
                why = f'the environment changed ({", ".join(sorted({k for k, _ in changed}))})'
            else:
                try:
                    os.write(standby.control,
                             encode_activation({k: env.get(k, '') for k in ACTIVATION_KEYS}))
                    os.close(standby.control)
                except OSError as err:
                    why = f'the standby could not be activated ({err})'
                else:
                    return WarmChild(standby.proc, warm=True)
            standby.drop()
        proc = subprocess.Popen(list(argv), env=dict(env), cwd=cwd, start_new_session=True,
                                preexec_fn=_die_with_supervisor)
        return WarmChild(proc, warm=False, why_cold=why)

    def discard(self, argv: Sequence[str], cwd: Path) -> None:
        """Drop the command's standby, if any."""
        with self._lock:
            standby = self._standbys.pop(_key(argv, cwd), None)
        if standby is not None:
            standby.done.set()
            standby.drop()

    def close(self) -> None:
        """Drop every standby."""
        with self._lock:
            standbys, self._standbys = list(self._standbys.values()), {}
        for standby in standbys:
            standby.done.set()
            standby.drop()
