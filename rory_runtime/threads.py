"""Names RORY's threads for the operating system, so that ``top -H``, ``ps -L`` and the
overhead benchmark tell them from the node's own: Python names a thread only for itself."""

from __future__ import annotations

import ctypes
import ctypes.util
import sys

_PR_SET_NAME = 15  # prctl(2)
_NAME_MAX = 15  # bytes, without the terminating NUL


def _libc() -> ctypes.CDLL | None:
    if not sys.platform.startswith('linux'):
        return None
    try:
        return ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6', use_errno=True)
    except OSError:
        return None


_LIBC = _libc()


def name_this_thread(name: str) -> None:
    """Give the calling thread ``name`` (cut to 15 bytes) in /proc; a no-op off Linux."""
    if _LIBC is not None:
        _LIBC.prctl(_PR_SET_NAME, name.encode()[:_NAME_MAX], 0, 0, 0)
