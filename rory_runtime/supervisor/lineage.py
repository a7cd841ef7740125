"""What may enter the recovery log R: the one place that keeps R exactly-once.

R is the only part of a node's log that the node did not write itself: the supervisor's ring
took it, from readers of its own, while the node was down. Everything else the node replays it
logged write-ahead. So the invariant "an identity is applied at most once per lineage of
checkpoints, in its publisher's order" (docs/architecture.md, "The invariant") comes down to
what :class:`Admission` lets into R:

* an identity the node already absorbed or logged (the newest checkpoint's windows and the
  segments after its cut; a segment may be an earlier R) is **known**: skipped;
* a message at or below the highest sequence number the node has of the same publisher, that
  the node does not have, is **never delivered**: the node's reader never received it (the
  ring matched that publisher first, or a re-matched transient-local reader was sent history
  the node's reader skipped). Replaying it would apply it out of its publisher's order, and a
  node that never crashed would never have seen it: dropped and counted;
* anything else is **new**, and from then on known too (R holds it once).

"The highest the node has of a publisher" is found from the ring's own view: the ring knows
each message's publisher GID (``rcl_take``), the node's log does not. A known identity seen
in the ring's backlog or later tells which publisher it was and raises that publisher's mark;
the backlog is judged after all of it has been looked at (:meth:`Admission.learn`), so a
message is judged against every later one of its publisher that the ring still holds.

:class:`SequenceWatch` sees the other side of the same numbers: a jump in one publisher's
sequence numbers is messages that never reached this host (:class:`InputGap`).
"""

from __future__ import annotations

import enum
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from ..log import LogEntry
from ..protocol import MessageId, seq_ranges

PublisherKey = tuple[str, bytes | None]
"""(topic, publisher GID); None where the GID is not known (one stream for the topic)."""


class Verdict(enum.Enum):
    """What :meth:`Admission.judge` decided for one message."""

    NEW = 'new'
    KNOWN = 'known'
    NEVER_DELIVERED = 'never_delivered'


@dataclass
class Admission:
    """Decides, message by message, what enters R.

    Args:
        known: Per topic, the identities the node absorbed or logged. Admitted identities
            are added to it, so a message reaches R at most once whatever path brings it
            again (the backlog of a later activation, a relay).
    """

    known: dict[str, set[MessageId]]
    # Per (topic, publisher): the highest sequence number the node has, logged or admitted.
    high: dict[PublisherKey, int] = field(default_factory=dict)
    # Per topic: sequence numbers dropped as never delivered, in the order met.
    never_delivered: dict[str, list[int]] = field(default_factory=dict)
    dropped_known: int = 0

    def learn(self, backlog: Iterable[LogEntry]) -> None:
        """Look at what the ring held at its activation before judging any of it: every known
        identity in it raises its publisher's mark, so that an older message of the same
        publisher is judged against it, wherever it stands in the backlog."""
        for entry in backlog:
            if entry.publisher is not None and entry.ident in self.known.get(entry.topic, ()):
                self._raise(entry)

    def judge(self, entry: LogEntry) -> Verdict:
        """Judge one message (the ring's later messages, one by one)."""
        seen = self.known.setdefault(entry.topic, set())
        if entry.ident in seen:
            self.dropped_known += 1
            if entry.publisher is not None:
                self._raise(entry)
            return Verdict.KNOWN
        if entry.publisher is not None and entry.seq <= self.high.get(
            (entry.topic, entry.publisher), 0
        ):
            self.never_delivered.setdefault(entry.topic, []).append(entry.seq)
            return Verdict.NEVER_DELIVERED
        seen.add(entry.ident)
        if entry.publisher is not None:
            self._raise(entry)
        return Verdict.NEW

    def _raise(self, entry: LogEntry) -> None:
        key = (entry.topic, entry.publisher)
        if entry.seq > self.high.get(key, 0):
            self.high[key] = entry.seq

    def never_delivered_summary(self) -> dict[str, dict[str, Any]]:
        """Per topic: how many were dropped as never delivered, and their sequence numbers."""
        return {topic: {'count': len(seqs), 'seqs': seq_ranges(sorted(seqs))}
                for topic, seqs in sorted(self.never_delivered.items()) if seqs}


@dataclass(frozen=True)
class InputGap:
    """Publication sequence numbers of an input that never reached this host."""

    topic: str
    first: int
    last: int
    seen_after_ns: int  # receive time of the message after the gap
    # Publishers the ring's reader was matched with when it saw the gap (-1: unknown). With
    # one, the numbers are that publisher's alone; judged then, not when the gap is reported
    # (by then the publisher may have finished and left).
    publishers: int = -1

    @property
    def missing(self) -> int:
        """How many messages."""
        return self.last - self.first + 1

    def to_json(self) -> dict[str, Any]:
        """For events.jsonl."""
        return {'topic': self.topic, 'first': self.first, 'last': self.last,
                'missing': self.missing}


class SequenceWatch:
    """Per publisher, the last sequence number seen; a jump is an :class:`InputGap`.

    A link outage longer than the DDS lease drops the readers; a re-matched volatile reader
    gets nothing of what was sent meanwhile, and a burst beyond a reader's history loses its
    oldest. Each publisher starts from what the node last logged of it (its mark in
    :class:`Admission`), or, where the ring's backlog showed no message of it that the node
    logged, from the topic's highest logged number if that publisher is the topic's only one
    in the backlog.

    Args:
        publishers: Publishers the topic's ring reader is matched with now (for
            :attr:`InputGap.publishers`).
    """

    def __init__(self, publishers: Callable[[str], int] | None = None) -> None:
        self._publishers = publishers
        self._last: dict[PublisherKey, int] = {}
        # Per topic: the highest number the node logged, for the one publisher whose own mark
        # the backlog did not show (None: whichever publisher comes first).
        self._fallback: dict[str, tuple[bytes | None, int]] = {}
        self.gaps: list[InputGap] = []

    def seed(self, admission: Admission, topic_marks: dict[str, int],
             backlog: Iterable[LogEntry]) -> None:
        """Start each publisher from what the node has of it (after :meth:`Admission.learn`).

        Args:
            admission: Its marks per publisher.
            topic_marks: Per topic, the highest sequence number the node logged.
            backlog: What the ring held at activation.
        """
        per_topic: dict[str, set[bytes | None]] = {}
        for entry in backlog:
            per_topic.setdefault(entry.topic, set()).add(entry.publisher)
        for topic, mark in topic_marks.items():
            publishers = per_topic.get(topic, set())
            if len(publishers) <= 1:
                self._fallback[topic] = (next(iter(publishers), None), mark)
        self._last.update(admission.high)

    def track(self, entry: LogEntry, verdict: Verdict) -> None:
        """Note one message the ring took (whatever its verdict)."""
        key = (entry.topic, entry.publisher)
        last = self._last.get(key)
        if last is None and entry.topic in self._fallback:
            publisher, mark = self._fallback[entry.topic]
            if publisher is None or publisher == entry.publisher:
                del self._fallback[entry.topic]
                last = mark
        if last is not None and entry.seq <= last:
            if verdict == Verdict.NEW:  # a new stream under one key: a restarted publisher
                self._last[key] = entry.seq  # whose GID the entry does not carry
            return
        if last is not None and entry.seq > last + 1 and verdict == Verdict.NEW:
            count = -1 if self._publishers is None else self._publishers(entry.topic)
            self.gaps.append(InputGap(entry.topic, last + 1, entry.seq - 1, entry.recv_ns, count))
        self._last[key] = entry.seq
