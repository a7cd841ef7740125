"""Taking a serialized message together with its publisher's GID.

rclpy's ``take_message`` returns the CDR bytes and four fields of the message info; it leaves
out ``publisher_gid``, the one field that says which writer sent the message. Publication
sequence numbers count per writer, so without it a reader cannot tell "an old message of this
publisher" from "a new message of another publisher on the same topic". The supervisor's ring
needs exactly that distinction (docs/architecture.md, "The invariant"), so it takes its
messages here, by calling ``rcl_take_serialized_message`` on the subscription's own rcl handle.

The structures below are those of ROS 2 Jazzy's ``rmw/types.h`` (``rmw_message_info_t`` with a
16-byte GID, ``rcutils_uint8_array_t``). A layout that does not match would misplace the GID;
the first message taken checks that the GID's implementation identifier is the rmw's own, and
the ring's tests take real messages from two publishers through it.
"""

from __future__ import annotations

import ctypes
from dataclasses import dataclass
from typing import Any

# rclpy's C extension links librcl and librcutils: importing it loads them into this process,
# where ctypes finds them by name.
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.utilities import get_rmw_implementation_identifier

from ..errors import RoryError

GID_SIZE = 16
"""``RMW_GID_STORAGE_SIZE`` in Jazzy (24 before Iron)."""

RCL_RET_OK = 0
RCL_RET_SUBSCRIPTION_TAKE_FAILED = 401
"""Nothing to take: the reader's history is empty."""


class _Allocator(ctypes.Structure):
    _fields_ = [
        ('allocate', ctypes.c_void_p),
        ('deallocate', ctypes.c_void_p),
        ('reallocate', ctypes.c_void_p),
        ('zero_allocate', ctypes.c_void_p),
        ('state', ctypes.c_void_p),
    ]


class _ByteArray(ctypes.Structure):
    """``rcutils_uint8_array_t``, alias ``rmw_serialized_message_t``."""

    _fields_ = [
        ('buffer', ctypes.POINTER(ctypes.c_uint8)),
        ('buffer_length', ctypes.c_size_t),
        ('buffer_capacity', ctypes.c_size_t),
        ('allocator', _Allocator),
    ]


class _Gid(ctypes.Structure):
    _fields_ = [
        ('implementation_identifier', ctypes.c_char_p),
        ('data', ctypes.c_uint8 * GID_SIZE),
    ]


class _MessageInfo(ctypes.Structure):
    """``rmw_message_info_t``."""

    _fields_ = [
        ('source_timestamp', ctypes.c_int64),
        ('received_timestamp', ctypes.c_int64),
        ('publication_sequence_number', ctypes.c_uint64),
        ('reception_sequence_number', ctypes.c_uint64),
        ('publisher_gid', _Gid),
        ('from_intra_process', ctypes.c_bool),
    ]


def _bind() -> tuple[Any, Any]:
    assert _rclpy is not None  # loaded, and with it the libraries below
    rcl = ctypes.CDLL('librcl.so')
    rcutils = ctypes.CDLL('librcutils.so')
    rcutils.rcutils_get_default_allocator.restype = _Allocator
    rcutils.rcutils_get_default_allocator.argtypes = []
    rcutils.rcutils_uint8_array_init.restype = ctypes.c_int
    rcutils.rcutils_uint8_array_init.argtypes = [
        ctypes.POINTER(_ByteArray), ctypes.c_size_t, ctypes.POINTER(_Allocator),
    ]
    rcutils.rcutils_uint8_array_fini.restype = ctypes.c_int
    rcutils.rcutils_uint8_array_fini.argtypes = [ctypes.POINTER(_ByteArray)]
    rcl.rcl_take_serialized_message.restype = ctypes.c_int
    rcl.rcl_take_serialized_message.argtypes = [
        ctypes.c_void_p, ctypes.POINTER(_ByteArray), ctypes.POINTER(_MessageInfo),
        ctypes.c_void_p,
    ]
    return rcl, rcutils


@dataclass(frozen=True, slots=True)
class Taken:
    """One message as the reader took it."""

    data: bytes  # CDR, exactly as received
    source_ns: int
    received_ns: int
    seq: int  # publication sequence number (the writer's; 1, 2, 3, ...)
    publisher: bytes  # the writer's GID (16 bytes)


class SerializedTaker:
    """Takes serialized messages with their full message info; one buffer, reused.

    Not thread-safe: one taker per thread (the ring has one thread that takes).
    """

    def __init__(self) -> None:
        self._rcl, self._rcutils = _bind()
        self._allocator = self._rcutils.rcutils_get_default_allocator()
        self._buffer = _ByteArray()
        ret = self._rcutils.rcutils_uint8_array_init(
            ctypes.byref(self._buffer), 0, ctypes.byref(self._allocator)
        )
        if ret != RCL_RET_OK:
            raise RoryError(f'rcl_take: cannot make a message buffer (rcutils error {ret})')
        self._info = _MessageInfo()
        self._closed = False
        self._checked = False

    def take(self, handle: Any) -> Taken | None:
        """The oldest message the subscription holds, or None.

        Args:
            handle: the subscription's rclpy handle (``Subscription.handle``), entered by the
                caller (``with handle:``) so that it cannot be destroyed meanwhile.

        Raises:
            RoryError: rcl failed for another reason than an empty history.
        """
        if self._closed:
            raise RoryError('rcl_take: taker is closed')
        ret = self._rcl.rcl_take_serialized_message(
            handle.pointer, ctypes.byref(self._buffer), ctypes.byref(self._info), None
        )
        if ret == RCL_RET_SUBSCRIPTION_TAKE_FAILED:
            return None
        if ret != RCL_RET_OK:
            raise RoryError(f'rcl_take_serialized_message failed (rcl error {ret})')
        info = self._info
        if not self._checked:
            self._check(info)
        return Taken(
            data=ctypes.string_at(self._buffer.buffer, self._buffer.buffer_length),
            source_ns=int(info.source_timestamp),
            received_ns=int(info.received_timestamp),
            seq=int(info.publication_sequence_number),
            publisher=bytes(info.publisher_gid.data),
        )

    def _check(self, info: _MessageInfo) -> None:
        expected = get_rmw_implementation_identifier()
        found = info.publisher_gid.implementation_identifier
        if found is None or found.decode(errors='replace') != expected:
            raise RoryError(
                f'rcl_take: the message info does not have the layout of ROS 2 Jazzy (GID '
                f'implementation {found!r}, expected {expected!r}); RORY reads the message info '
                'of Jazzy on 64-bit Linux'
            )
        self._checked = True

    def close(self) -> None:
        """Free the buffer."""
        if not self._closed:
            self._closed = True
            self._rcutils.rcutils_uint8_array_fini(ctypes.byref(self._buffer))
