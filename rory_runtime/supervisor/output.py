"""Node output, prefixed: each node's stdout and stderr lines reach the supervisor's own with
``[name] `` in front, as ``ros2 launch`` prints them, so that several nodes under one
supervisor can be told apart (``prefix_output`` in supervise.yaml; on by default when there is
more than one node).

Every node process (and the standby, which becomes one) writes into two pipes of its own; one
thread here reads them all and writes whole lines. A line is written once it is complete, so
two nodes' lines never interleave mid-line; a partial line waits for its end, or is written
as it is when the pipe closes (the process died mid-line) or when it grows past
:data:`LONGEST_LINE`. A standby's lines carry ``[rory-standby]`` until it becomes a node.
"""

from __future__ import annotations

import contextlib
import os
import selectors
import threading
import time
from typing import BinaryIO

LONGEST_LINE = 16384
"""Bytes of a line without its end that are written anyway, so that one process cannot make
the supervisor hold an unbounded partial line."""

STANDBY_LABEL = 'rory-standby'


class Streams:
    """One process's pair of pipes: the write ends go to the process (``child_fds``), the
    read ends to the :class:`OutputPrefixer` that opened them."""

    def __init__(self, label: str, out_fd: int, err_fd: int) -> None:
        self.label = label
        self.child_fds: tuple[int, int] = (out_fd, err_fd)

    def relabel(self, label: str) -> None:
        """From now on its lines carry ``label`` (a standby that became a node)."""
        self.label = label

    def close_child_ends(self) -> None:
        """Once the process has its copies: the pipes then close when it ends."""
        for fd in self.child_fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self.child_fds = (-1, -1)


class _Pipe:
    def __init__(self, streams: Streams, target: BinaryIO) -> None:
        self.streams = streams
        self.target = target
        self.pending = b''


class OutputPrefixer:
    """Copies what node processes write to ``stdout`` and ``stderr`` (the supervisor's own
    binary streams), each line prefixed with its process's label."""

    def __init__(self, stdout: BinaryIO, stderr: BinaryIO) -> None:
        self._stdout = stdout
        self._stderr = stderr
        self._selector = selectors.DefaultSelector()
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_r, False)
        self._selector.register(self._wake_r, selectors.EVENT_READ, None)
        self._lock = threading.Lock()  # the selector's registrations, and the writes
        self._closed = False
        self._thread = threading.Thread(target=self._pump, name='rory-output', daemon=True)
        self._thread.start()

    def open(self, label: str) -> Streams:
        """New pipes for a process whose lines carry ``label``."""
        out_r, out_w = os.pipe()
        err_r, err_w = os.pipe()
        streams = Streams(label, out_w, err_w)
        with self._lock:
            for fd, target in ((out_r, self._stdout), (err_r, self._stderr)):
                os.set_blocking(fd, False)
                self._selector.register(fd, selectors.EVENT_READ, _Pipe(streams, target))
        os.write(self._wake_w, b'x')  # the pump's select() takes the new pipes in
        return streams

    def _pump(self) -> None:
        while True:
            with self._lock:
                if self._closed:
                    return
            for key, _ in self._selector.select():
                if key.data is None:
                    with contextlib.suppress(BlockingIOError):
                        os.read(self._wake_r, 4096)
                    continue
                self._drain(key.fd, key.data)

    def _drain(self, fd: int, pipe: _Pipe) -> None:
        try:
            data = os.read(fd, 65536)
        except BlockingIOError:
            return
        except OSError:
            data = b''
        if data:
            pipe.pending += data
            *lines, pipe.pending = pipe.pending.split(b'\n')
            if len(pipe.pending) >= LONGEST_LINE:
                lines.append(pipe.pending)
                pipe.pending = b''
            self._write(pipe, lines)
            return
        if pipe.pending:  # it ended mid-line
            self._write(pipe, [pipe.pending])
            pipe.pending = b''
        with self._lock:
            self._selector.unregister(fd)
        os.close(fd)

    def _write(self, pipe: _Pipe, lines: list[bytes]) -> None:
        with self._lock:
            _emit(pipe, lines)

    def close(self, timeout: float = 2.0) -> None:
        """Write what is still in the pipes (up to ``timeout`` for processes to end), stop."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                open_pipes = len(self._selector.get_map()) - 1  # less the wake-up pipe
            if open_pipes <= 0:
                break
            time.sleep(0.02)
        with self._lock:
            self._closed = True
        os.write(self._wake_w, b'x')
        self._thread.join(timeout)
        with self._lock:
            for key in list(self._selector.get_map().values()):
                if key.data is not None and key.data.pending:
                    _emit(key.data, [key.data.pending])
                with contextlib.suppress(OSError):
                    os.close(key.fd)
            self._selector.close()
        os.close(self._wake_w)


def _emit(pipe: _Pipe, lines: list[bytes]) -> None:
    """Write whole lines with the pipe's label in front (the caller holds the lock)."""
    if not lines:
        return
    prefix = f'[{pipe.streams.label}] '.encode()
    with contextlib.suppress(OSError, ValueError):
        pipe.target.write(b''.join(prefix + line + b'\n' for line in lines))
        pipe.target.flush()
