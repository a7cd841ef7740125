"""One supervised node as /diagnostics shows it (``diagnostics.py`` turns it into a
``DiagnosticStatus``): plain data, made by ``ManagedNode.health`` without ROS."""

from __future__ import annotations

import time
from dataclasses import dataclass

from ..freshness import Verdict
from .states import NodeState


@dataclass(frozen=True)
class NodeHealth:
    """One supervised node as /diagnostics shows it."""

    node: str
    state: NodeState
    method: str
    pid: int | None
    incarnation: int
    crashes: int
    last_recovery_ms: float | None
    last_recovery_age_s: float | None
    last_checkpoint_age_s: float | None
    standby: str  # 'ready', 'starting', 'none' or 'off'
    # Seconds past what the checkpoint interval lets a running node go without one, if late.
    checkpoint_overdue_s: float | None = None
    # The node's last checkpoint failure (a variable that cannot be saved, a full disk), until
    # a checkpoint succeeds.
    checkpoint_error: str | None = None
    # Why the supervisor gave up (FATAL), in its own words.
    fatal_reason: str | None = None
    # What the last restore did with each key variable.
    freshness: Verdict | None = None
    # The release gate's service, while the node waits at it (GATED).
    gate_service: str | None = None


@dataclass
class NodeRecord:
    """What a node's /diagnostics say beyond its state and process, kept as it happens."""

    crashes: int = 0
    last_recovery: tuple[float, float] | None = None  # (total ms, monotonic when)
    fatal_reason: str | None = None  # why the supervisor gave up (FATAL), in its own words
    freshness: Verdict | None = None  # what the last restore did with each key variable


def age(since: float | None, now: float | None = None) -> float | None:
    """Seconds since a monotonic time, or None."""
    if since is None:
        return None
    return (time.monotonic() if now is None else now) - since
