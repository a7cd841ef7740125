"""The supervisor's end of the status socket (rory_runtime/status_socket.py): one Unix datagram
socket for all its nodes, read by one thread.

Each datagram is one signed status message; the thread hands its text to ``deliver`` (the
supervisor's ``post_status``, which checks the signature and the node it names and queues
it for the main loop), as the DDS status readers' callbacks did.
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import socket
import threading
from collections.abc import Callable

from ..status_socket import MAX_DATAGRAM, to_env
from ..threads import name_this_thread

_logger = logging.getLogger('rory.supervisor')


class StatusInbox:
    """Binds the socket (abstract namespace, named after this process) and reads it.

    Args:
        deliver: Called on the inbox's thread with each datagram's text.
    """

    def __init__(self, deliver: Callable[[str], None]) -> None:
        self._deliver = deliver
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        name = f'\0rory-status-{os.getpid()}-{secrets.token_hex(4)}'
        self._socket.bind(name)
        self.address = to_env(name)
        """Where nodes send their statuses, as the environment spells it (``@rory-status-...``)."""
        self._closed = False
        self._thread = threading.Thread(target=self._run, name='rory-inbox', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        name_this_thread('rory-inbox')
        while True:
            try:
                data = self._socket.recv(MAX_DATAGRAM + 1)
            except OSError:
                if self._closed:
                    return
                raise
            if not data and self._closed:
                return
            try:
                text = data.decode()
            except UnicodeDecodeError:
                _logger.warning('[rory] ignoring a status datagram that is not UTF-8')
                continue
            try:
                self._deliver(text)
            except Exception:
                _logger.exception('[rory] a status could not be handled')

    def close(self) -> None:
        """Stop reading: a last empty datagram to itself wakes the thread."""
        self._closed = True
        with contextlib.suppress(OSError):
            self._socket.sendto(b'', self._socket.getsockname())
        self._thread.join(timeout=1.0)
        self._socket.close()
