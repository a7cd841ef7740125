"""One process of a supervised node, as the supervisor knows it: its pid, its HELLO, its
release, and what the supervisor sends it on its shadow topic (SYNC, RELEASE, OPEN). A new
:class:`Incarnation` at each spawn (its heartbeat and kill: ``watchdog.Watchdog``)."""

from __future__ import annotations

from dataclasses import dataclass

from .. import protocol
from ..protocol import HelloStatus, ReplayPace
from .ports import EnvelopePort, RingPort
from .process import Child


@dataclass
class Incarnation:
    """What the supervisor knows of one process of a node."""

    number: int
    sync_nonce: int  # a SYNCED answering any SYNC with it proves the shadow path
    child: Child | None = None  # its process, until it has ended or been stopped
    # The writer on its shadow topic (protocol.replay_topic: one per incarnation), made by the
    # ROS side at its spawn; earlier ones are retired once no replay streams on them.
    replay_pub: EnvelopePort | None = None
    hello: HelloStatus | None = None
    running_since: float | None = None  # when it was released, while it runs
    sync_sent: float = 0.0
    synced_counts: dict[str, int] | None = None  # its live publishers per input, from SYNCED
    release_sent: bool = False
    checkpoint_error: str | None = None  # its last checkpoint failure, until one succeeds

    def _send(self, raw: bytes) -> None:
        assert self.replay_pub is not None  # made at its spawn
        self.replay_pub.publish(raw)

    def send_sync(self, now: float) -> None:
        """SYNC, sent again each ``gate.SYNC_PERIOD`` until SYNCED answers."""
        self.sync_sent = now
        self._send(protocol.pack_sync(self.number, self.sync_nonce))

    def send_release(self, next_segment: int) -> None:
        """RELEASE after a fresh start (once; the node answers RELEASED)."""
        self.release_sent = True
        self._send(protocol.pack_release(self.number, next_segment, 0))

    def send_open(self) -> None:
        """OPEN: the release gate opened."""
        self._send(protocol.pack_open(self.number))

    def synced(self, nonce: int, live_publishers: dict[str, int]) -> bool:
        """A SYNCED: whether it is the first that answers this process's SYNC."""
        if nonce != self.sync_nonce or self.synced_counts is not None:
            return False
        self.synced_counts = dict(live_publishers)
        return True

    def armed(self, ring: RingPort | None) -> bool:
        """The ring matches every publisher the node's own readers have (fresh start)."""
        if self.synced_counts is None or ring is None:
            return False
        counts = ring.publisher_counts()
        return all(counts.get(t, 0) >= n for t, n in self.synced_counts.items())

    def restored_cut(self) -> int | None:
        """The last log segment the restored checkpoint holds: replay starts after it."""
        hello = self.hello
        return None if hello is None or hello.restored is None else hello.restored.cut

    def replay_pace(self, configured: ReplayPace | None) -> ReplayPace:
        """The supervisor config's pace, else the node's own (keyvars.yaml), else fast.

        Fast is the default since callbacks get the clock readings, ticks, parameter changes
        and requests they had live (docs/architecture.md, "Timers and the clock"); paced is
        for nodes that read time RORY cannot replay (docs/keyvars.md).
        """
        if configured is not None:
            return configured
        wanted = None if self.hello is None else self.hello.replay
        return ReplayPace(wanted) if wanted in {p.value for p in ReplayPace} else ReplayPace.FAST

    def checkpoint_interval(self) -> float:
        """The node's checkpoint interval, as its HELLO said (2 s before one)."""
        interval = None if self.hello is None else self.hello.interval
        return float(interval or 2.0)
