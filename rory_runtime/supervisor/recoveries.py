"""One node's recoveries, one at a time: which :class:`~.recovery.Recovery` a crash starts or
carries on, how one ends, and its input gaps, each said once along the way
(:class:`~.recovery.GapReports`).

A crash before the release carries the current recovery on (R keeps recording, the safe state
stays held, its time counts from the first crash); a crash after its S4, while the ring still
relays (the handover), stops it and starts a recovery of its own. A recovery ends when the
node has switched every input to its live reader (or exited on its own), is stopped with the
supervisor (the safe state as it is), or is given up (the safe state held).
:class:`Recoveries` keeps the current one for ``ManagedNode``, which decides when.
"""

from __future__ import annotations

from collections.abc import Callable

from ..log import LogEntry, SegmentStore
from ..store import CheckpointStore
from .ports import EventSink, RingPort, SafetyPort
from .recovery import GapReports, Recovery


class Recoveries:
    """The recoveries of one node.

    Args:
        node_id: The node's name.
        safety: The safe state (S1 to S4).
        segments: The node's message log.
        checkpoints: The node's checkpoints.
        clock: Monotonic seconds.
        events: The event log (input gaps).
    """

    def __init__(self, node_id: str, safety: SafetyPort, segments: SegmentStore,
                 checkpoints: CheckpointStore, clock: Callable[[], float],
                 events: EventSink) -> None:
        self.node_id = node_id
        self._safety = safety
        self._segments = segments
        self._checkpoints = checkpoints
        self._clock = clock
        self.current: Recovery | None = None
        self.gaps = GapReports(node_id, events)  # input gaps, each said once

    def start(self, crashed: float, crashed_ns: int, ring: RingPort | None,
              early: list[LogEntry] | None = None) -> Recovery:
        """A new recovery, of a crash at ``crashed`` (monotonic s) and ``crashed_ns`` (wall
        ns): S1 and S2 (``Recovery.begin``, R from ``early``, if the ring kept any)."""
        rec = self.current = Recovery(
            node_id=self.node_id, crashed=crashed, crashed_ns=crashed_ns, safety=self._safety,
            ring=ring, segments=self._segments, checkpoints=self._checkpoints,
            clock=self._clock,
        )
        rec.begin(early)
        return rec

    def crashed(self, at: float, at_ns: int, recovering: bool, ring: RingPort | None,
                take_early: Callable[[], list[LogEntry] | None]) -> Recovery:
        """The node crashed (``recovering``: before the release): the recovery that goes on."""
        rec = self.current
        if rec is not None and recovering:
            # Died before its release: the same recovery goes on, R keeps recording.
            rec.again(at)
            return rec
        if rec is not None:
            # Crashed during the handover of an earlier recovery, whose S4 released the safe
            # state: that one ends here, and this crash is a recovery of its own.
            rec.stop()
            self.gaps.report(rec)  # also those held back for a switch that never came
        return self.start(at, at_ns, ring, take_early())

    def report_gaps(self) -> None:
        """Say the current recovery's input gaps not said yet."""
        if self.current is not None:
            self.gaps.report(self.current)

    def end(self) -> None:
        """The recovery is over: the node is back on every input, or it exited (the safe
        state is left if S4 has not left it)."""
        if self.current is not None:
            self.current.finish()
            self.gaps.report(self.current)  # after finish: none is held back any more
            self.current = None

    def stop(self) -> None:
        """The supervisor stops: the safe state stays as it is (held if the node had not been
        released)."""
        if self.current is not None:
            self.current.stop()
            self.gaps.report(self.current)  # after stop: none is held back any more

    def give_up(self) -> None:
        """The node is given up: the safe state stays held."""
        if self.current is not None:
            self.current.give_up()
