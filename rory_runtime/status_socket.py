"""Statuses from a node's runtime to its supervisor, outside DDS: a Unix datagram socket.

A node and its supervisor run on one computer (docs/multihost.md: one supervisor per computer,
for the nodes it hosts), so the runtime's statuses (HELLO, RELEASED, CHECKPOINT, ERROR, ...)
need no DDS writer in the node: no entity, no discovery, no reliable writer's heartbeats, and a
HELLO that arrives as soon as it is sent instead of once DDS has matched a writer with a reader
(docs/architecture.md, "Nothing in the node's executor").

The supervisor binds one socket in Linux's abstract namespace (no file to clean up; gone with
the process) and gives its address to each node in ``RORY_STATUS_SOCKET`` (protocol.py,
``ENV_STATUS``), ``@`` standing for the leading NUL as ``ss`` prints it. Each datagram is one
status message, JSON signed with the run's key (protocol.encode_status), so a datagram from any
other process is refused as a forged DDS status was.

:class:`StatusSender` is the node's side: :meth:`~StatusSender.send` queues the text and returns
(the executor thread never waits on the supervisor, which may be busy or frozen); a daemon
thread sends the queue in order.
"""

from __future__ import annotations

import logging
import queue
import socket
import threading
import time

_logger = logging.getLogger('rory.status')

MAX_DATAGRAM = 200_000
"""Largest status sent (bytes): a Unix datagram must fit the socket's send buffer, 208 KB by
default on Linux. A HELLO of a node with a hundred inputs is a few tens of KB."""

_ABSTRACT = '@'


def to_env(address: str) -> str:
    """The environment's spelling of an abstract socket address (``@name`` for ``\\0name``)."""
    return _ABSTRACT + address[1:] if address.startswith('\0') else address


def from_env(value: str) -> str:
    """The socket address an environment value names."""
    return '\0' + value[1:] if value.startswith(_ABSTRACT) else value


class StatusSender:
    """A node's statuses to its supervisor, sent in order by a side thread.

    Args:
        address: The supervisor's socket (as :func:`from_env` gives it).
    """

    def __init__(self, address: str) -> None:
        self._address = address
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._queue: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._said: set[str] = set()
        self._thread = threading.Thread(target=self._run, name='rory-status', daemon=True)
        self._thread.start()

    def send(self, text: str) -> None:
        """Queue one status (thread-safe, never blocks)."""
        self._queue.put(text.encode())

    def close(self, timeout: float = 2.0) -> None:
        """Send what is queued (at most ``timeout`` seconds), then stop."""
        self._queue.put(None)
        self._thread.join(timeout)
        self._socket.close()

    def _run(self) -> None:
        while (data := self._queue.get()) is not None:
            self._send(data)

    def _send(self, data: bytes) -> None:
        if len(data) > MAX_DATAGRAM:
            self._say(f'a status of {len(data)} bytes is larger than {MAX_DATAGRAM}: not sent')
            return
        for attempt in range(3):
            try:
                self._socket.sendto(data, self._address)
                return
            except (ConnectionRefusedError, FileNotFoundError):
                # No supervisor bound there (it ended): nothing will read it.
                self._say(f'no supervisor at {to_env(self._address)}: statuses are dropped')
                return
            except OSError as err:
                if attempt == 2:
                    self._say(f'a status could not be sent: {err}')
                    return
                time.sleep(0.01)

    def _say(self, line: str) -> None:
        if line not in self._said:
            self._said.add(line)
            _logger.error('[rory] %s', line)
