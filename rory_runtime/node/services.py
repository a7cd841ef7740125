"""A node's service servers as inputs (docs/architecture.md, "Services").

A request is logged before the node's handler runs and replayed in order among the messages,
ticks and parameter changes; in replay the handler's response goes nowhere (the caller of the
crashed process got none). Until release the service is left out of the executor's wait set
(:class:`HeldUntilRelease`), so requests that arrive while the node recovers wait in the
service's queue and are served, and logged, after S4: the isolation topics get.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from rclpy.callback_groups import CallbackGroup
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import UInt8MultiArray

# A request is logged as the bytes of its CDR inside a UInt8MultiArray: bag readers have no
# service types, and this way they still read the record.
RECORD_TYPE = 'std_msgs/msg/UInt8MultiArray'


def pack_request(request: Any) -> bytes:
    """The record's bytes for one request."""
    return bytes(serialize_message(UInt8MultiArray(data=bytes(serialize_message(request)))))


def unpack_request(data: bytes, request_type: type) -> Any:
    """The request :func:`pack_request` packed.

    Raises:
        ValueError: ``data`` does not hold a ``request_type``.
    """
    try:
        wrapped = deserialize_message(data, UInt8MultiArray)
        return deserialize_message(bytes(wrapped.data), request_type)
    except RuntimeError as err:  # rclpy's RMWError
        raise ValueError(f'not a {request_type.__name__}: {err}') from None


class HeldUntilRelease(CallbackGroup):
    """A service's callback group, closed until the node is released.

    rclpy's executors leave an entity whose group cannot execute out of the wait set, so a
    request is neither taken nor spun on: it waits in the service's queue.
    """

    def __init__(self, inner: CallbackGroup, released: Callable[[], bool]) -> None:
        super().__init__()
        self.inner = inner
        self._released = released

    def add_entity(self, entity: Any) -> None:
        self.inner.add_entity(entity)

    def has_entity(self, entity: Any) -> bool:
        return self.inner.has_entity(entity)

    def can_execute(self, entity: Any) -> bool:
        return self._released() and self.inner.can_execute(entity)

    def beginning_execution(self, entity: Any) -> bool:
        return self._released() and self.inner.beginning_execution(entity)

    def ending_execution(self, entity: Any) -> None:
        self.inner.ending_execution(entity)
