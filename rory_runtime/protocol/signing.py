"""The HMAC tag that envelopes and statuses carry, of the key the supervisor draws for each run
(``ENV_SECRET``): another participant on the domain cannot feed a recovering node forged
messages or steer its recovery."""

from __future__ import annotations

import hashlib
import hmac
from typing import Final

TAG_BYTES: Final = 16
"""Length of an HMAC-SHA256 tag as carried (truncated, as RFC 2104 allows)."""


def tag(key: bytes, data: bytes) -> bytes:
    """The tag of ``data`` under ``key``: its HMAC-SHA256, the first :data:`TAG_BYTES`."""
    return hmac.new(key, data, hashlib.sha256).digest()[:TAG_BYTES]
