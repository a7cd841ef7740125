"""What the node tells its supervisor: statuses on the status socket, errors once each.

Every part of the node side (router, applier, output gate, checkpointer) reports through one
:class:`Reporter`, handed to it as ``status`` and ``error``: none of them calls back into the
runtime core for that.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from .. import protocol, status_socket
from ..protocol import CheckpointFailure, ErrorStatus, Status

if TYPE_CHECKING:
    from rclpy.node import Node

_logger = logging.getLogger('rory.runtime')


class Reporter:
    """Statuses to the supervisor's socket (status_socket.py), signed; errors logged and sent once.

    Args:
        node_id: The node's name in the supervisor config.
        incarnation: This process's number.
        secret: The run's key (None: unsigned).
        socket: The supervisor's status socket (None: statuses are dropped).
    """

    def __init__(self, node_id: str, incarnation: int, secret: bytes | None,
                 socket: str | None) -> None:
        self._node_id = node_id
        self._incarnation = incarnation
        self._secret = secret
        # Statuses go to the supervisor's socket, not over DDS (status_socket.py).
        self._sender = None if socket is None else status_socket.StatusSender(socket)
        self.reported_errors: set[str] = set()
        # The node whose logger errors go to, once it exists (on_constructed).
        self.node: Node | None = None

    def status(self, status: Status) -> None:
        """Send ``status`` (queued: the executor never waits on the supervisor)."""
        if self._sender is None:
            return
        self._sender.send(protocol.encode_status(
            status, self._node_id, self._incarnation, key=self._secret, sent_ns=time.time_ns()))

    def error(self, message: str, checkpoint: CheckpointFailure | None = None) -> None:
        """Log ``message`` and send it as an ERROR status, once; ``checkpoint``: it says a
        checkpoint was not taken, and why (the supervisor reads that, not the message)."""
        if message in self.reported_errors:
            return
        self.reported_errors.add(message)
        if self.node is not None and self.node.context.ok():
            self.node.get_logger().error(f'[rory] {message}')
        else:
            # With its context shut down (rclpy's SIGINT handler does it before the exit-time
            # checkpoint), the node's logger adds a failure to publish on /rosout.
            _logger.error('[rory] %s', message)
        self.status(ErrorStatus(message=message, checkpoint=checkpoint))

    def close(self) -> None:
        """Send what is queued, then stop."""
        if self._sender is not None:
            self._sender.close()
