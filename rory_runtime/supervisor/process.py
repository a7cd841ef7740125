"""Processes: spawning, signalling and reaping supervised nodes, and restart pacing.

OS calls sit behind the :class:`Launcher` and :class:`Child` protocols so that unit tests can
drive the supervisor's transitions with fakes; :class:`PopenLauncher` is the real one.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import signal
import subprocess
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Protocol

from .. import protocol
from ..dds import node_profile_env
from ..protocol import Mode
from .config import Backoff, NodeConfig

_PR_SET_PDEATHSIG = 1

STOP_GRACE = (3.0, 2.0)
"""Seconds to wait after SIGINT, then after SIGTERM, before SIGKILL."""


class Child(Protocol):
    """A running node process."""

    @property
    def pid(self) -> int:
        """Process id."""
        ...

    def wait(self, timeout: float | None = None) -> int:
        """Block until the process ends; its return code (negative: killed by that signal)."""
        ...

    def poll(self) -> int | None:
        """Return code if the process has ended, else None."""
        ...

    def send_signal(self, sig: int) -> None:
        """Deliver a signal; no error if the process is already gone."""
        ...


class Launcher(Protocol):
    """Starts node processes."""

    def spawn(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path,
              label: str = '') -> Child:
        """Start ``argv`` with exactly ``env`` in ``cwd``; ``label`` names it in its output
        lines when they are prefixed (supervisor/output.py)."""
        ...

    def prepare(self, argv: Sequence[str], env: Mapping[str, str],
                cwd: Path) -> list[int] | None:
        """Get ready for the next ``spawn`` of ``argv`` (warm standbys): the pids started now
        (none if ready already), or None when ``argv`` cannot have a standby."""
        ...

    def discard(self, argv: Sequence[str], cwd: Path) -> None:
        """Forget what ``prepare`` made for ``argv``."""
        ...

    def close(self) -> None:
        """Release everything prepared."""
        ...


def _die_with_supervisor() -> None:
    # A node must not outlive its supervisor unsupervised: a restarted supervisor recovers it
    # from the store instead. Runs in the child between fork and exec.
    libc = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6', use_errno=True)
    libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() == 1:  # the supervisor died before prctl took effect
        os._exit(1)


class _PopenChild:
    """A node process started with exec: always cold (``why_cold`` says why, if the launcher
    knows)."""

    warm = False

    def __init__(self, proc: subprocess.Popen[bytes], why_cold: str = '') -> None:
        self._proc = proc
        self.why_cold = why_cold

    @property
    def pid(self) -> int:
        return self._proc.pid

    def wait(self, timeout: float | None = None) -> int:
        return self._proc.wait(timeout)

    def poll(self) -> int | None:
        return self._proc.poll()

    def send_signal(self, sig: int) -> None:
        if self._proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self._proc.send_signal(sig)


class PopenLauncher:
    """Spawns real processes, each in its own session and bound to the supervisor's life.

    Its own session keeps a Ctrl-C at the terminal from reaching the nodes directly: the
    supervisor stops them itself, in order. Must be called from the supervisor's main thread
    (PR_SET_PDEATHSIG follows the thread that forked).
    """

    def spawn(self, argv: Sequence[str], env: Mapping[str, str], cwd: Path,
              why_cold: str = '', output: Sequence[int] = ()) -> _PopenChild:
        """Start a node process; ``output``: its stdout and stderr, if not ours."""
        out, err = output if output else (None, None)
        proc = subprocess.Popen(
            list(argv),
            env=dict(env),
            cwd=cwd,
            stdout=out,
            stderr=err,
            start_new_session=True,
            preexec_fn=_die_with_supervisor,
        )
        return _PopenChild(proc, why_cold)

    def prepare(self, argv: Sequence[str], env: Mapping[str, str],
                cwd: Path) -> list[int] | None:
        """Nothing to prepare: every start is cold."""
        return None

    def discard(self, argv: Sequence[str], cwd: Path) -> None:
        """Nothing prepared."""

    def close(self) -> None:
        """Nothing prepared."""


def reap(child: Child, label: str, exited: Callable[[int], None]) -> None:
    """Wait for ``child`` to end on a thread of its own (``rory-reap-<label>``), which hands
    ``exited`` its exit code."""
    threading.Thread(target=lambda: exited(child.wait()), name=f'rory-reap-{label}',
                     daemon=True).start()


def describe_exit(code: int) -> str:
    """'killed by SIGKILL' or 'exit status 3'."""
    if code < 0:
        try:
            return f'killed by {signal.Signals(-code).name}'
        except ValueError:
            return f'killed by signal {-code}'
    return f'exit status {code}'


class RestartPolicy:
    """Decides how long to wait before a restart, and when to give up.

    The count of consecutive crashes resets once a start sticks (ran ``stable_after`` seconds),
    unlike launch's respawn whose retry count never resets.
    """

    def __init__(self, backoff: Backoff) -> None:
        self.backoff = backoff
        self.consecutive = 0

    def on_crash(self, ran_for: float) -> float | None:
        """Delay before restarting after a crash, or None to give up.

        Args:
            ran_for: Seconds the crashed process had been released and running (0 if it died
                during recovery).
        """
        if ran_for >= self.backoff.stable_after:
            self.consecutive = 0
        self.consecutive += 1
        if self.consecutive > self.backoff.max_restarts:
            return None
        if self.consecutive == 1:
            return self.backoff.initial
        return float(min(self.backoff.maximum, self.backoff.step * 2 ** (self.consecutive - 2)))


def node_environment(cfg: NodeConfig, mode: Mode, incarnation: int, *, store: Path,
                     quarantine: str, secret: bytes, channel: str,
                     status_address: str) -> dict[str, str]:
    """The environment of one process of a node: the supervisor's own, the node's ``env``, and
    what its runtime reads (``protocol.ENV_*``: who it is, where its store and supervisor are,
    how it starts)."""
    env = dict(os.environ)
    env.update(cfg.env)
    env.update(
        {
            protocol.ENV_NODE: cfg.name,
            protocol.ENV_STORE: str(store),
            protocol.ENV_INCARNATION: str(incarnation),
            protocol.ENV_METHOD: cfg.method.value,
            protocol.ENV_MODE: mode.value,
            protocol.ENV_QUARANTINE: quarantine,
            protocol.ENV_SECRET: secret.hex(),
            protocol.ENV_CHANNEL: channel,
            protocol.ENV_STATUS: status_address,
            'PYTHONUNBUFFERED': '1',
        }
    )
    env.update(node_profile_env(env))  # a cold node's discovery: rory_runtime/dds
    if cfg.checkpoint_interval is not None:
        env[protocol.ENV_INTERVAL] = repr(cfg.checkpoint_interval)
    else:
        env.pop(protocol.ENV_INTERVAL, None)
    if mode == Mode.RECOVER and cfg.release_gate is not None:
        env[protocol.ENV_GATED] = '1'
    else:
        env.pop(protocol.ENV_GATED, None)
    return env


def stop_child(child: Child) -> None:
    """Stop a node's process: SIGINT, then SIGTERM, then SIGKILL (:data:`STOP_GRACE`)."""
    for sig, grace in zip(
        (signal.SIGINT, signal.SIGTERM, signal.SIGKILL), (*STOP_GRACE, 5.0), strict=True
    ):
        child.send_signal(sig)
        try:
            child.wait(timeout=grace)
            break
        except Exception:
            continue
