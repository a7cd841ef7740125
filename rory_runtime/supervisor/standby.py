"""Starting nodes, the supervisor's side: forks of the zygote, and one warm standby for all.

:class:`ForkLauncher` is a :class:`~.process.Launcher`. A node whose command is a Python program
(``python FILE ...`` or ``python -m MODULE ...``, this interpreter, the zygote's import
environment) starts as a fork of the zygote (:mod:`.zygote`): its imports are already in
memory. ``prepare()`` keeps a *standby* ready: a fork that has called ``rclpy.init`` and whose
DDS participant the graph already knows, so a recovered node receives its first message
within milliseconds rather than after the 1-2 s a new participant takes to be discovered. One
standby serves every node with the same ``rclpy.init`` (:func:`~.zygote.init_signature`): a
robot's nodes under one supervisor usually share one. ``spawn()`` activates it when it fits;
when it is gone (two nodes crashed at once, or it died) the node is forked cold from the
zygote, and says why. Any other command is started with ``exec``, cold.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import RoryError
from .output import STANDBY_LABEL, OutputPrefixer, Streams
from .process import Child, PopenLauncher
from .states import LOG_PREFIX
from .zygote import (
    Zygote,
    activation_line,
    forkable,
    init_arguments,
    init_signature,
)

_logger = logging.getLogger('rory.supervisor')

IMPORT_ENV_PREFIXES = ('PYTHON', 'LD_', 'OPENBLAS_', 'OMP_', 'MKL_')
"""Environment that shapes what a process imports: a node whose values differ from the
zygote's cannot be forked from it."""


def _import_env(env: Mapping[str, str]) -> dict[str, str]:
    return {k: v for k, v in env.items() if k.startswith(IMPORT_ENV_PREFIXES)}


class PidChild:
    """A node process this supervisor did not start with Popen but is the parent of (a fork of
    the zygote, re-parented here). Like Popen: one thread reaps, the others see the code."""

    def __init__(self, pid: int, *, warm: bool, why_cold: str = '') -> None:
        self._pid = pid
        self.warm = warm
        self.why_cold = why_cold
        self._code: int | None = None
        self._reaping = threading.Lock()
        self._done = threading.Event()

    @property
    def pid(self) -> int:
        return self._pid

    def _reaped(self, status: int) -> int:
        self._code = os.waitstatus_to_exitcode(status)
        self._done.set()
        return self._code

    def poll(self) -> int | None:
        if self._done.is_set():
            return self._code
        if not self._reaping.acquire(blocking=False):
            return None  # another thread is in waitpid
        try:
            if self._done.is_set():
                return self._code
            pid, status = os.waitpid(self._pid, os.WNOHANG)
            return self._reaped(status) if pid else None
        except ChildProcessError:
            return self._reaped(0) if not self._done.is_set() else self._code
        finally:
            self._reaping.release()

    def wait(self, timeout: float | None = None) -> int:
        if timeout is None:
            with self._reaping:
                if not self._done.is_set():
                    try:
                        _, status = os.waitpid(self._pid, 0)
                    except ChildProcessError:
                        status = 0
                    self._reaped(status)
            assert self._code is not None
            return self._code
        deadline = time.monotonic() + timeout
        while (code := self.poll()) is None:
            left = deadline - time.monotonic()
            if left <= 0:
                raise subprocess.TimeoutExpired(str(self._pid), timeout)
            self._done.wait(min(left, 0.01))
        return code

    def send_signal(self, sig: int) -> None:
        if not self._done.is_set():
            with contextlib.suppress(ProcessLookupError):
                os.kill(self._pid, sig)


@dataclass
class Standby:
    """The waiting process of one init signature."""

    child: PidChild
    control: int  # write end of its control pipe
    started: float
    wanted_by: set[tuple[tuple[str, ...], str]] = field(default_factory=set)
    ready_at: float | None = None
    done: threading.Event = field(default_factory=threading.Event)
    streams: Streams | None = None  # its output pipes, when lines are prefixed

    @property
    def pid(self) -> int:
        return self.child.pid

    def drop(self) -> None:
        """Kill it and reap it (it holds nothing)."""
        self.done.set()
        with contextlib.suppress(OSError):
            os.close(self.control)
        self.child.send_signal(signal.SIGKILL)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.child.wait(timeout=5.0)


def _key(argv: Sequence[str], cwd: Path) -> tuple[tuple[str, ...], str]:
    return tuple(argv), str(cwd)


class ForkLauncher:
    """Forks nodes from the zygote, from the shared standby when one is waiting.

    Args:
        zygote: The fork server (started before the supervisor's ``rclpy.init``); without one
            every start is an ``exec``, cold.
        clock: Monotonic clock.
        output: Prefixes every process's output lines with its label; None: processes write
            to the supervisor's own stdout and stderr.
    """

    def __init__(self, zygote: Zygote | None,
                 clock: Callable[[], float] = time.monotonic,
                 output: OutputPrefixer | None = None) -> None:
        self.zygote = zygote
        self._clock = clock
        self.output = output
        self._standbys: dict[Hashable, Standby] = {}
        self._lock = threading.Lock()
        self._exec = PopenLauncher()

    def _forkable(self, argv: Sequence[str],
                  env: Mapping[str, str]) -> tuple[Hashable | None, str]:
        """The node's init signature, or None and why it cannot be forked."""
        if self.zygote is None:
            return None, 'no fork server'
        program = forkable(argv)
        if program is None:
            return None, 'not a python FILE or python -m MODULE command'
        mine, zygote = _import_env(env), _import_env(self.zygote.env)
        if mine != zygote:
            changed = sorted({k for k, _ in set(mine.items()) ^ set(zygote.items())})
            return None, f'its import environment differs ({", ".join(changed)})'
        return init_signature(program, env), ''

    def prepare(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path) -> int | None:
        """Have a standby waiting for the next ``spawn(argv, ...)``: the one its init signature
        shares, or a new fork. Its pid, or None when this command cannot have one."""
        signature, _why = self._forkable(argv, env)
        if signature is None or self.zygote is None:
            return None
        with self._lock:
            standby = self._standbys.get(signature)
            if standby is not None and standby.child.poll() is None:
                standby.wanted_by.add(_key(argv, cwd))
                return standby.pid
        program = forkable(argv)
        assert program is not None
        args = init_arguments(signature)
        init_args = [program.argv[0], *(('--ros-args', *args) if args else ())]
        streams = self.output.open(STANDBY_LABEL) if self.output is not None else None
        try:
            forked = self.zygote.fork_standby(init_args, env, cwd,
                                              streams.child_fds if streams else ())
        finally:
            if streams is not None:
                streams.close_child_ends()
        standby = Standby(PidChild(forked.pid, warm=True), forked.control, self._clock(),
                          {_key(argv, cwd)}, streams=streams)
        with self._lock:
            old = self._standbys.pop(signature, None)
            self._standbys[signature] = standby
        if old is not None:
            old.drop()
        self._watch_ready(standby, forked.ready)
        return standby.pid

    def _watch_ready(self, standby: Standby, ready: int) -> None:
        def watch() -> None:
            try:
                got = os.read(ready, 1)
            except OSError:
                got = b''
            finally:
                os.close(ready)
            if got:
                standby.ready_at = self._clock()
                _logger.info('%s standby pid %d ready in %.0f ms', LOG_PREFIX, standby.pid,
                             (standby.ready_at - standby.started) * 1000)
            elif not standby.done.is_set():
                _logger.warning('%s standby pid %d ended before it was ready (%s)', LOG_PREFIX,
                                standby.pid, standby.child.poll())

        threading.Thread(target=watch, name='rory-standby', daemon=True).start()

    def standby(self, argv: Sequence[str], cwd: Path) -> Standby | None:
        """The standby this command would start from, if one waits."""
        with self._lock:
            for standby in self._standbys.values():
                if _key(argv, cwd) in standby.wanted_by:
                    return standby
        return None

    def spawn(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path,
              label: str = '') -> Child:
        """Activate the shared standby if it fits, else fork cold, else exec cold."""
        signature, why = self._forkable(argv, env)
        if signature is None or self.zygote is None:
            return self._exec_spawn(argv, env, cwd, why, label)
        with self._lock:
            standby = self._standbys.pop(signature, None)
        why = 'no standby waiting'
        if standby is not None:
            standby.done.set()
            code = standby.child.poll()
            if code is not None:
                why = f'the standby had exited ({code})'
            else:
                if standby.streams is not None:
                    standby.streams.relabel(label or STANDBY_LABEL)
                try:
                    os.write(standby.control, activation_line(argv, env, cwd))
                    os.close(standby.control)
                except OSError as err:
                    why = f'the standby could not be activated ({err})'
                else:
                    return standby.child
            standby.drop()
        streams = self.output.open(label) if self.output is not None else None
        try:
            pid = self.zygote.fork_node(argv, env, cwd, streams.child_fds if streams else ())
        except RoryError as err:
            return self._exec_spawn(argv, env, cwd, f'{why}; {err}', label)
        finally:
            if streams is not None:
                streams.close_child_ends()
        return PidChild(pid, warm=False, why_cold=why)

    def _exec_spawn(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path, why: str,
                    label: str) -> Child:
        streams = self.output.open(label) if self.output is not None else None
        try:
            return self._exec.spawn(argv, env, cwd, why, streams.child_fds if streams else ())
        finally:
            if streams is not None:
                streams.close_child_ends()

    def discard(self, argv: Sequence[str], cwd: Path) -> None:
        """This command no longer wants a standby; the shared one goes once none does."""
        drop = []
        with self._lock:
            for signature, standby in list(self._standbys.items()):
                standby.wanted_by.discard(_key(argv, cwd))
                if not standby.wanted_by:
                    drop.append(self._standbys.pop(signature))
        for standby in drop:
            standby.drop()

    def close(self) -> None:
        """Drop every standby and end the zygote."""
        with self._lock:
            standbys, self._standbys = list(self._standbys.values()), {}
        for standby in standbys:
            standby.drop()
        if self.zygote is not None:
            self.zygote.close()
        if self.output is not None:
            self.output.close()
