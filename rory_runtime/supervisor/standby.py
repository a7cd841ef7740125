"""Starting nodes, the supervisor's side: forks of the zygote, and a pool of warm standbys.

:class:`ForkLauncher` is a :class:`~.process.Launcher`. A node whose command is a Python program
(``python FILE ...`` or ``python -m MODULE ...``, this interpreter, the zygote's import
environment) starts as a fork of the zygote (:mod:`.zygote`): its imports are already in
memory. ``prepare()`` keeps *standbys* ready: forks that have called ``rclpy.init`` and whose
DDS participants the graph already knows, so a recovered node receives its first message
within milliseconds rather than after the discovery a new participant waits for
(docs/performance.md, "Where a slow cold start waits"). A pool of ``pool_size`` standbys
serves every node with the same ``rclpy.init`` (:func:`~.zygote.init_signature`): a robot's
nodes under one supervisor usually share one pool, and one bad message that takes down
several of them at once finds a standby for each, up to the pool's size. ``spawn()``
activates one when it fits; when none is left (more nodes struck together than the pool
holds, or they died) the node starts from one of the pool's *spare forks*, made ahead without
``rclpy.init`` (one for each node beyond the pool's size; ``spare_forks: false`` turns them
off: docs/performance.md, "Spare forks"), and else is forked cold from the zygote; a node
that starts cold says why. The pool is filled again :data:`REFILL_DELAY` after it was taken
from. Any other command is started with ``exec``, cold.
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
    """One waiting process."""

    child: PidChild
    control: int  # write end of its control pipe
    started: float
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


CommandKey = tuple[tuple[str, ...], str]
"""A node's command line and folder: what asks for a standby."""


@dataclass
class StandbyPool:
    """The standbys of one init signature, for every command that can become one of them, and
    its spare forks: one for each such command beyond the pool's size, so that when every one
    of them is struck at once, those the standbys do not cover start from a fork already made
    rather than from a round trip to the zygote on the supervisor's main loop."""

    waiting: list[Standby] = field(default_factory=list)
    spares: list[Standby] = field(default_factory=list)
    wanted_by: set[CommandKey] = field(default_factory=set)
    # When a standby or spare was last taken (activated or found dead): the refill waits
    # REFILL_DELAY after it, so that new ones do not compete with recoveries for the CPU.
    taken_at: float | None = None

    def best(self) -> Standby | None:
        """The one to hand out next: the longest ready, else the longest starting."""
        return _longest_ready(self.waiting)

    def spares_wanted(self, pool_size: int) -> int:
        """Spare forks to keep: the commands that want this pool, beyond its standbys."""
        return max(0, len(self.wanted_by) - pool_size)


def _longest_ready(held: Sequence[Standby]) -> Standby | None:
    ready = [s for s in held if s.ready_at is not None]
    return min(ready or held, key=lambda s: s.started, default=None)


REFILL_DELAY = 1.0
"""Seconds after a standby was taken before its pool is filled again: a crash that took it
has its recovery done by then (tens of milliseconds warm), and several nodes struck together
take theirs within that time."""


def _key(argv: Sequence[str], cwd: Path) -> CommandKey:
    return tuple(argv), str(cwd)


class ForkLauncher:
    """Forks nodes from the zygote, from a pool of standbys when one is waiting.

    Args:
        zygote: The fork server (started before the supervisor's ``rclpy.init``); without one
            every start is an ``exec``, cold.
        clock: Monotonic clock.
        output: Prefixes every process's output lines with its label; None: processes write
            to the supervisor's own stdout and stderr.
        pool_size: Standbys kept waiting per init signature.
        spares: Whether each pool also keeps its spare forks (:class:`StandbyPool`).
    """

    def __init__(self, zygote: Zygote | None,
                 clock: Callable[[], float] = time.monotonic,
                 output: OutputPrefixer | None = None,
                 pool_size: int = 1, spares: bool = True) -> None:
        self.zygote = zygote
        self._clock = clock
        self.output = output
        self.pool_size = pool_size
        self.spares_kept = spares
        self._pools: dict[Hashable, StandbyPool] = {}
        self._lock = threading.Lock()
        self._exec = PopenLauncher()

    def _spares_wanted(self, pool: StandbyPool) -> int:
        return pool.spares_wanted(self.pool_size) if self.spares_kept else 0

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

    def prepare(self, argv: Sequence[str], env: Mapping[str, str],
                cwd: Path) -> list[int] | None:
        """Have the pool of standbys that ``spawn(argv, ...)`` would start from full, with its
        spare forks: the pool its init signature shares, with what is missing forked now (not
        within :data:`REFILL_DELAY` of one being taken from it). The pids of the standbys
        started (none when the pool is full or the refill must wait; spares are not named),
        or None when this command cannot have a standby. Called from one thread (the
        supervisor's main loop)."""
        signature, _why = self._forkable(argv, env)
        if signature is None or self.zygote is None:
            return None
        now = self._clock()
        with self._lock:
            pool = self._pools.setdefault(signature, StandbyPool())
            pool.wanted_by.add(_key(argv, cwd))
            dead = [s for s in (*pool.waiting, *pool.spares) if s.child.poll() is not None]
            for standby in dead:
                (pool.waiting if standby in pool.waiting else pool.spares).remove(standby)
            if dead:
                pool.taken_at = now
            waits = pool.taken_at is not None and now - pool.taken_at < REFILL_DELAY
            missing = 0 if waits else self.pool_size - len(pool.waiting)
            spares_missing = 0 if waits else self._spares_wanted(pool) - len(pool.spares)
        for standby in dead:
            _logger.warning('%s %s pid %d had ended (%s); another takes its place', LOG_PREFIX,
                            'standby' if standby.child.warm else 'spare fork', standby.pid,
                            standby.child.poll())
            standby.drop()
        started = []
        for _ in range(missing):
            standby = self._fork_standby(signature, argv, env, cwd)
            with self._lock:
                pool = self._pools.setdefault(signature, StandbyPool())
                pool.waiting.append(standby)
            started.append(standby.pid)
        for _ in range(spares_missing):
            spare = self._fork_standby(signature, argv, env, cwd, spare=True)
            with self._lock:
                pool = self._pools.setdefault(signature, StandbyPool())
                pool.spares.append(spare)
        return started

    def full(self, argv: Sequence[str], cwd: Path) -> bool:
        """The pool this command starts from holds its standbys and spares, all alive: what
        :meth:`prepare` would find (without its environment and init signature to compute)."""
        with self._lock:
            pool = self._pool_of(argv, cwd)
            return pool is not None and (
                len(pool.waiting) >= self.pool_size
                and len(pool.spares) >= self._spares_wanted(pool)
                and all(s.child.poll() is None for s in (*pool.waiting, *pool.spares)))

    def _fork_standby(self, signature: Hashable, argv: Sequence[str], env: Mapping[str, str],
                      cwd: Path, *, spare: bool = False) -> Standby:
        assert self.zygote is not None
        program = forkable(argv)
        assert program is not None
        args = init_arguments(signature)
        init_args = [program.argv[0], *(('--ros-args', *args) if args else ())]
        streams = self.output.open(STANDBY_LABEL) if self.output is not None else None
        try:
            forked = self.zygote.fork_standby(init_args, env, cwd,
                                              streams.child_fds if streams else (), spare=spare)
        finally:
            if streams is not None:
                streams.close_child_ends()
        standby = Standby(PidChild(forked.pid, warm=not spare), forked.control, self._clock(),
                          streams=streams)
        self._watch_ready(standby, forked.ready)
        return standby

    def _watch_ready(self, standby: Standby, ready: int) -> None:
        def watch() -> None:
            try:
                got = os.read(ready, 1)
            except OSError:
                got = b''
            finally:
                os.close(ready)
            what = 'standby' if standby.child.warm else 'spare fork'
            if got:
                standby.ready_at = self._clock()
                _logger.log(logging.INFO if standby.child.warm else logging.DEBUG,
                            '%s %s pid %d ready in %.0f ms', LOG_PREFIX, what, standby.pid,
                            (standby.ready_at - standby.started) * 1000)
            elif not standby.done.is_set():
                _logger.warning('%s %s pid %d ended before it was ready (%s)', LOG_PREFIX,
                                what, standby.pid, standby.child.poll())

        threading.Thread(target=watch, name='rory-standby', daemon=True).start()

    def _pool_of(self, argv: Sequence[str], cwd: Path) -> StandbyPool | None:
        """The pool this command starts from (the caller holds the lock)."""
        key = _key(argv, cwd)
        return next((pool for pool in self._pools.values() if key in pool.wanted_by), None)

    def standby(self, argv: Sequence[str], cwd: Path) -> Standby | None:
        """The standby this command would start from next, if one waits."""
        with self._lock:
            pool = self._pool_of(argv, cwd)
            return None if pool is None else pool.best()

    def standbys(self, argv: Sequence[str], cwd: Path) -> list[Standby]:
        """Every standby this command could start from."""
        with self._lock:
            pool = self._pool_of(argv, cwd)
            return [] if pool is None else list(pool.waiting)

    def spares(self, argv: Sequence[str], cwd: Path) -> list[Standby]:
        """Every spare fork this command could start from."""
        with self._lock:
            pool = self._pool_of(argv, cwd)
            return [] if pool is None else list(pool.spares)

    def _take(self, signature: Hashable) -> Standby | None:
        """A standby of the pool, else one of its spare forks, taken out of it."""
        with self._lock:
            pool = self._pools.get(signature)
            if pool is None:
                return None
            for held in (pool.waiting, pool.spares):
                standby = _longest_ready(held)
                if standby is not None:
                    held.remove(standby)
                    pool.taken_at = self._clock()
                    return standby
            return None

    def spawn(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path,
              label: str = '') -> Child:
        """Activate a standby of the pool if one fits, else fork cold, else exec cold."""
        signature, why = self._forkable(argv, env)
        if signature is None or self.zygote is None:
            return self._exec_spawn(argv, env, cwd, why, label)
        with self._lock:
            pooled = signature in self._pools
        why = (f'no standby waiting (the pool of {self.pool_size} is in use)' if pooled
               else 'no standby waiting')
        while (standby := self._take(signature)) is not None:
            standby.done.set()
            what = 'standby' if standby.child.warm else 'spare fork'
            code = standby.child.poll()
            if code is not None:
                why = f'the {what} had exited ({code})'
            else:
                if standby.streams is not None:
                    standby.streams.relabel(label or STANDBY_LABEL)
                try:
                    os.write(standby.control, activation_line(argv, env, cwd))
                    os.close(standby.control)
                except OSError as err:
                    why = f'the {what} could not be activated ({err})'
                else:
                    if not standby.child.warm:
                        standby.child.why_cold = f'{why}; from a spare fork'
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
        """This command no longer wants a standby; a pool goes once no command wants it, and
        keeps a spare fork only for each command beyond its standbys."""
        drop: list[Standby] = []
        with self._lock:
            for signature, pool in list(self._pools.items()):
                pool.wanted_by.discard(_key(argv, cwd))
                if not pool.wanted_by:
                    gone = self._pools.pop(signature)
                    drop.extend((*gone.waiting, *gone.spares))
                    continue
                while len(pool.spares) > self._spares_wanted(pool):
                    drop.append(pool.spares.pop())
        for standby in drop:
            standby.drop()

    def close(self) -> None:
        """Drop every standby and end the zygote."""
        with self._lock:
            pools, self._pools = list(self._pools.values()), {}
        for pool in pools:
            for standby in (*pool.waiting, *pool.spares):
                standby.drop()
        if self.zygote is not None:
            self.zygote.close()
        if self.output is not None:
            self.output.close()
