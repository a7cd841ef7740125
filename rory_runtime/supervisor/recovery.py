"""Crash recovery of one node, step by step (the paper's S1-S4).

* **S1 safe state** - :meth:`Recovery.s1_safe_state`: the configured safe actions are published
  at once and held until S4.
* **S2 isolation** - :meth:`Recovery.s2_isolate`: the supervisor's ring takes over the node's
  inputs, so nothing published while the node is down is lost: what the ring held at the crash
  and all that arrives afterwards go to the *recovery log* R, a log segment of its own, minus
  what the node had already logged. The replacement process starts isolated (its runtime mutes
  its publishers, holds its timers and does not apply live messages).
* **S3 data recovery** - :meth:`Recovery.s3_restart` spawns the process, whose runtime restores
  the newest valid checkpoint before any callback; :meth:`Recovery.s3_replay` then streams every
  logged message after that checkpoint's cut, then R, on the node's shadow topic, in receive
  order, paced by the recorded gaps or as fast as the node takes them. When the stream has
  caught up with R it seals R and sends RELEASE.
* **S4 release** - :meth:`Recovery.s4_release`: the node has unmuted its outputs and started its
  timers; the safe state is released. Afterwards the supervisor keeps relaying what its ring
  receives until the node reports, topic by topic, that its live subscription carries the same
  messages (the handover, see ``node/routing.py``).

:class:`Recovery` runs these steps for the supervisor's ``ManagedNode``, which decides when (a
crash, a HELLO, a SYNCED, a RELEASED) and never takes a step itself: S1 and S2 start in
:meth:`Recovery.begin`, S2 again in :meth:`Recovery.again` (a crash before the release) and
:meth:`Recovery.join_ring` (the ring exists once the node has named its inputs); the safe state
is left in one place, :meth:`Recovery._leave_safe_state`, once per recovery: at S4, or at
:meth:`Recovery.finish` when the node ended on its own before S4. A recovery that ends without
its node back (:meth:`Recovery.give_up`, :meth:`Recovery.stop`) keeps the safe state held.

The invariant behind "no message lost, none applied twice": the node's log segments, then R,
hold every message of the node's inputs exactly once, in receive order; a checkpoint's cut
says which prefix of that sequence it absorbed; the node skips any identity it has already
applied.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rosbags.interfaces import Qos

from .. import protocol
from ..errors import LogError
from ..freshness import Verdict as Freshness
from ..freshness import describe as describe_freshness
from ..inflight import InFlight
from ..log import LogEntry, SegmentStore, SegmentWriter
from ..protocol import (
    FLAG_RELAY,
    RELAY_KEEPALIVE_S,
    MessageId,
    Method,
    ReleasedStatus,
    ReplayPace,
    pack_alive,
    pack_msg,
    pack_release,
)
from ..store import CheckpointStore
from .lineage import Admission, InputGap, SequenceWatch, Verdict
from .poison import Quarantined, died_on_json
from .ports import Capture, EnvelopePort, EventSink, RingPort, SafetyPort
from .states import LOG_PREFIX
from .watchdog import Beat

_logger = logging.getLogger('rory.supervisor')

GAP_HOLD_S = 15.0
"""How long a gap the relay shows (seen after R was sealed) waits for its topic's switch before
it is reported as the ring saw it.

The node may have received some of those messages on its live reader and applied them (its
SWITCHED status names them, ``live_only``); the gap reported leaves them out. A node switches
a topic once three relayed messages also came live, or after its live messages waited 10 s
with nothing of the topic relayed (``routing.RELAY_WAIT_NS``): 15 s covers both for inputs of
0.2 Hz and up. A gap still held then (a handover that does not end: the publisher stopped) is
reported whole; the ``switched`` event lists what the node applied of it, if it switches later.
A gap is also reported whole when the recovery stops before its topic switched."""


def absorbed_identities(
    checkpoints: CheckpointStore, segments: SegmentStore
) -> dict[str, set[MessageId]]:
    """Identities of every message the node has already absorbed or logged, per topic.

    The newest readable checkpoint's windows cover what it absorbed recently (older segments
    are gone); the segments after its cut cover the rest.
    """
    ckpt = checkpoints.latest_valid()
    known: dict[str, set[MessageId]] = {}
    cut = None
    if ckpt is not None:
        cut = ckpt.cut
        for topic, idents in ckpt.windows.items():
            known.setdefault(topic, set()).update((s, q) for s, q in idents)
    for topic, logged in segments.identities_after(cut).items():
        if protocol.is_input_topic(topic):  # ticks and clock readings are not messages
            known.setdefault(topic, set()).update(logged)
    return known


class RecoveryLog:
    """R: what arrived for the node since its crash (and the ring's backlog), as a segment.

    A :class:`~.ring.RingSink`. What enters it is decided by :class:`~.lineage.Admission`
    alone. Entries added after :meth:`seal` are the post-release relay: the node logs those
    itself.
    """

    def __init__(self, segments: SegmentStore, known: dict[str, set[MessageId]],
                 offered_qos: Callable[[str], Sequence[Qos]] | None = None,
                 publishers: Callable[[str], int] | None = None) -> None:
        self._offered_qos = offered_qos
        self.number = segments.next_number()
        self._writer: SegmentWriter | None = segments.open(self.number)
        # What the node last logged per topic, before R (for the summary and the gap check).
        self._seeded = {topic: max(seq for _, seq in ids) for topic, ids in known.items()
                        if ids}
        self.admission = Admission(known)
        self._sequence = SequenceWatch(publishers)
        self.entries: list[LogEntry] = []
        # Consumed from the front by the streamer, so a topic that never switches back to its
        # live reader does not make this grow.
        self.relay: deque[LogEntry] = deque()
        self.sealed = False
        # How many gaps were seen before the seal: the later ones were seen in the relay.
        self.gaps_before_seal: int | None = None
        self.cond = threading.Condition()

    @property
    def gaps(self) -> list[InputGap]:
        """Sequence numbers that never reached this host (caller holds :attr:`cond`)."""
        return self._sequence.gaps

    @property
    def dropped_known(self) -> int:
        """Messages skipped because the node already had them."""
        return self.admission.dropped_known

    def add_backlog(self, entries: list[LogEntry]) -> None:
        """Record what the ring held at its activation, in receive order."""
        with self.cond:
            self.admission.learn(entries)
            self._sequence.seed(self.admission, self._seeded, entries)
            for entry in entries:
                self._admit(entry)
            self.cond.notify_all()

    def add(self, entry: LogEntry) -> None:
        """Record one message (called from the ring's thread)."""
        with self.cond:
            self._admit(entry)
            self.cond.notify_all()

    def _admit(self, entry: LogEntry) -> None:
        verdict = self.admission.judge(entry)
        self._sequence.track(entry, verdict)
        if verdict != Verdict.NEW:
            return
        if self.sealed:
            self.relay.append(entry)
            return
        assert self._writer is not None
        try:
            qos = self._offered_qos
            self._writer.write(
                entry.topic, entry.msgtype, entry.recv_ns, entry.source_ns, entry.seq,
                entry.data,
                offered_qos=None if qos is None else lambda: qos(entry.topic),
            )
        except LogError as err:
            _logger.error('%s recovery log: %s', LOG_PREFIX, err)
        self.entries.append(entry)

    def summary(self) -> dict[str, dict[str, int | None]]:
        """Per topic: the last sequence number logged before R, what R itself holds, and how
        many messages were dropped as never delivered to the node.

        Goes into the ``recovered`` event, so that a loss found later can be placed: before
        R (the logs), inside it, or after it (the handover).
        """
        with self.cond:
            held: dict[str, list[int]] = {}
            for entry in self.entries:
                held.setdefault(entry.topic, []).append(entry.seq)
            never = self.admission.never_delivered
            topics = sorted(set(held) | set(self._seeded) | set(never))
            return {
                topic: {
                    'logged_through': self._seeded.get(topic),
                    'entries': len(held.get(topic, ())),
                    'first_seq': min(held[topic]) if topic in held else None,
                    'last_seq': max(held[topic]) if topic in held else None,
                    'never_delivered': len(never.get(topic, ())),
                }
                for topic in topics
            }

    def never_delivered(self) -> dict[str, dict[str, Any]]:
        """Per topic, messages dropped as never delivered (:class:`~.lineage.Admission`)."""
        with self.cond:
            return self.admission.never_delivered_summary()

    def seal(self) -> None:
        """Close the segment: from now on entries are relayed, not part of the log."""
        with self.cond:
            if self.sealed:
                return
            self.sealed = True
            self.gaps_before_seal = len(self._sequence.gaps)
            if self._writer is not None:
                self._writer.close()
                self._writer = None
            self.cond.notify_all()

    def close(self) -> None:
        """Release the file (on supervisor stop)."""
        self.seal()


@dataclass
class Timings:
    """Monotonic timestamps of one recovery (seconds); None until reached."""

    crashed: float
    s1_done: float | None = None
    s2_done: float | None = None
    spawned: float | None = None
    hello: float | None = None
    restore_ms: float = 0.0
    synced: float | None = None
    release_sent: float | None = None
    s4_done: float | None = None

    def breakdown(self) -> dict[str, float]:
        """Milliseconds per step, and the total (crash detected -> released)."""

        def ms(a: float | None, b: float | None) -> float:
            return round((b - a) * 1000.0, 2) if a is not None and b is not None else 0.0

        return {
            'total_ms': ms(self.crashed, self.s4_done),
            's1_ms': ms(self.crashed, self.s1_done),
            's2_ms': ms(self.s1_done, self.s2_done),
            'restart_ms': round(max(0.0, ms(self.spawned, self.hello) - self.restore_ms), 2),
            'restore_ms': round(self.restore_ms, 2),
            'sync_ms': ms(self.hello, self.synced),
            'replay_ms': ms(self.synced, self.release_sent),
            's4_ms': ms(self.release_sent or self.hello, self.s4_done),
        }


def readings_first(entries: Iterable[LogEntry]) -> Iterator[LogEntry]:
    """The log's records in order, except that an event's clock readings (logged while its
    callback ran, so after it) come just before the event: the node then has them when it
    replays the event (docs/architecture.md, "Timers and the clock")."""
    event: LogEntry | None = None
    readings: list[LogEntry] = []
    try:
        for entry in entries:
            if entry.topic == protocol.CLOCK_RECORD and event is not None:
                readings.append(entry)
                continue
            if event is not None:
                yield from readings
                yield event
                readings.clear()
            event = entry
    except LogError:
        # What was read before the failure is still sent.
        if event is not None:
            yield from readings
            yield event
        raise
    if event is not None:
        yield from readings
        yield event


class ReplayStreamer(threading.Thread):
    """Feeds the node's shadow topic: logged segments, then R; RELEASE; then the relay."""

    def __init__(
        self,
        publisher: EnvelopePort,
        incarnation: int,
        backlog: Iterator[LogEntry],
        rlog: RecoveryLog,
        pace: ReplayPace,
        crashed_ns: int,
        on_released: Callable[[int], None],
    ) -> None:
        super().__init__(name=f'rory-replay-{incarnation}', daemon=True)
        self._pub = publisher
        self._incarnation = incarnation
        self._backlog = backlog
        self._rlog = rlog
        self._pace = pace
        self._crashed_ns = crashed_ns
        self._on_released = on_released
        self._stopped = threading.Event()
        self.switched: set[str] = set()
        self.sent = 0
        self.error: str | None = None

    def stop(self) -> None:
        """Stop streaming (the node died again, or the supervisor stops)."""
        self._stopped.set()
        with self._rlog.cond:
            self._rlog.cond.notify_all()

    def _send(self, entry: LogEntry, flags: int = 0) -> None:
        self._pub.publish(
            pack_msg(
                self._incarnation,
                topic=entry.topic,
                recv_ns=entry.recv_ns,
                source_ns=entry.source_ns,
                seq=entry.seq,
                data=entry.data,
                flags=flags,
            )
        )
        self.sent += 1

    def run(self) -> None:
        try:
            self._stream()
        except LogError as err:
            self.error = str(err)
            _logger.error('%s replay failed: %s', LOG_PREFIX, err)

    def _stream(self) -> None:
        first_ns: int | None = None
        wall0 = time.monotonic()

        def pace(entry: LogEntry) -> None:
            nonlocal first_ns
            # The paper's mode replays at the recorded gaps; what arrived after the crash is
            # queued and goes as fast as the node takes it, or the stream would never catch up.
            if self._pace != ReplayPace.PACED or entry.recv_ns > self._crashed_ns:
                return
            if first_ns is None:
                first_ns = entry.recv_ns
                return
            delay = wall0 + (entry.recv_ns - first_ns) / 1e9 - time.monotonic()
            if delay > 0:
                self._stopped.wait(delay)

        for entry in readings_first(self._backlog):
            if self._stopped.is_set():
                return
            pace(entry)
            self._send(entry)
        index = 0
        while not self._stopped.is_set():
            with self._rlog.cond:
                if index >= len(self._rlog.entries):
                    # Caught up: seal R so everything after this RELEASE is a relay.
                    self._rlog.seal()
                    self._pub.publish(
                        pack_release(self._incarnation, self._rlog.number + 1, self.sent)
                    )
                    break
                entry = self._rlog.entries[index]
            index += 1
            pace(entry)
            self._send(entry)
        if self._stopped.is_set():
            return
        self._on_released(self.sent)
        self._relay()

    def _relay(self) -> None:
        """Relay what the ring receives; with nothing to send for RELAY_KEEPALIVE_S, send an
        ALIVE, so that the node does not take an idle relay for a dead supervisor (its ring may
        receive nothing for a while: a link outage longer than the DDS lease)."""
        last_sent = time.monotonic()
        while not self._stopped.is_set():
            entry = None
            with self._rlog.cond:
                while not self._rlog.relay and not self._stopped.is_set():
                    idle = time.monotonic() - last_sent
                    if idle >= RELAY_KEEPALIVE_S:
                        break
                    self._rlog.cond.wait(RELAY_KEEPALIVE_S - idle)
                if self._stopped.is_set():
                    return
                if self._rlog.relay:
                    entry = self._rlog.relay.popleft()
            if entry is None:
                self._pub.publish(pack_alive(self._incarnation))
                last_sent = time.monotonic()
            elif entry.topic not in self.switched:
                self._send(entry, FLAG_RELAY)
                last_sent = time.monotonic()


@dataclass
class Recovery:
    """The recovery of one crash of one node (it may take several processes to finish)."""

    node_id: str
    crashed: float  # the clock's seconds at the crash
    crashed_ns: int  # time.time_ns() at the crash, the clock of message receive times
    safety: SafetyPort
    ring: RingPort | None
    segments: SegmentStore
    checkpoints: CheckpointStore
    clock: Callable[[], float] = time.monotonic  # the supervisor's (ports.py)
    timings: Timings = field(init=False)
    rlog: RecoveryLog | None = None
    streamer: ReplayStreamer | None = None
    crashes: int = 1
    safe_state_held: bool = field(default=False, init=False)  # from S1 until it is left
    # Topics the node switched to their live readers, and per topic the sequence numbers it
    # applied from its live reader that the relay never delivered (SWITCHED's live_only).
    switched: set[str] = field(default_factory=set, init=False)
    live_only: dict[str, set[int]] = field(default_factory=dict, init=False)
    # Each gap as it is reported (narrowed by live_only), fixed once reported; the clock when
    # a gap the relay showed was first held back; whether the recovery has stopped.
    _reported: dict[InputGap, list[InputGap]] = field(default_factory=dict, init=False)
    _held_since: dict[InputGap, float] = field(default_factory=dict, init=False)
    _stopped: bool = field(default=False, init=False)
    # The messages its crashes died applying and those quarantined as poison on the way
    # (poison.py), in crash order: the ``recovered`` event names them, so that a state that
    # lacks a message says which one and why.
    died_on: list[InFlight] = field(default_factory=list, init=False)
    quarantined: list[Quarantined] = field(default_factory=list, init=False)

    def __post_init__(self) -> None:
        self.timings = Timings(crashed=self.crashed)

    def begin(self, early: list[LogEntry] | None = None) -> None:
        """The crash is judged: S1, then S2.

        Args:
            early: What the ring took since the node's heartbeat went late, if it did
                (:class:`EarlyCapture`): R starts from it.
        """
        self.s1_safe_state()
        self.s2_isolate(early)

    def s1_safe_state(self) -> None:
        """S1: hold the safe state until S4."""
        self.safety.hold(self.node_id)
        self.safe_state_held = True
        self.timings.s1_done = self.clock()

    def s2_isolate(self, early: list[LogEntry] | None = None) -> None:
        """S2: the ring takes over the node's inputs; their messages go to R, not to the node.

        Without a ring yet (the node had not named its inputs, or a supervisor resumes from
        its store) only the time is taken: the ring joins later (:meth:`join_ring`). With an
        R that is still open nothing changes: it keeps recording.
        """
        if self.ring is not None and (self.rlog is None or self.rlog.sealed):
            self.rlog = RecoveryLog(
                self.segments, absorbed_identities(self.checkpoints, self.segments),
                self.ring.offered_qos, self.ring.publisher_count,
            )
            self.ring.activate(self.rlog, early)
        if self.timings.s2_done is None:  # a later crash of the same recovery is not S2 time
            self.timings.s2_done = self.clock()

    def join_ring(self, ring: RingPort) -> None:
        """The ring exists now (the node named its inputs in its HELLO): S2 with it."""
        self.ring = ring
        self.s2_isolate()

    def again(self, crashed: float) -> None:
        """The replacement died before release: same recovery, next process.

        R keeps recording and the safe state stays held. If R was already sealed, what came
        after the seal went to the relay, and the dead process may have taken some of it: a
        new R takes over from the ring's backlog, minus what the closed R and the logs hold.
        """
        self.crashes += 1
        if self.streamer is not None:
            self.streamer.stop()
            self.streamer = None
        self.timings.spawned = self.timings.hello = self.timings.synced = None
        self.timings.release_sent = None
        self.s2_isolate()

    def s3_restart(self, spawn: Callable[[], None]) -> None:
        """S3: start the replacement process (its runtime restores before any callback)."""
        spawn()
        self.timings.spawned = self.clock()

    def on_hello(self, restore_ms: float) -> None:
        """The replacement is up and has restored."""
        self.timings.hello = self.clock()
        self.timings.restore_ms = restore_ms

    def s3_replay(
        self,
        publisher: EnvelopePort,
        incarnation: int,
        cut: int | None,
        pace: ReplayPace,
        on_released: Callable[[int], None],
    ) -> None:
        """S3: stream the log after ``cut`` and then R on the shadow topic."""
        assert self.rlog is not None
        self.timings.synced = self.clock()
        # Everything logged after the cut, up to R (which the streamer reads from memory).
        backlog = self.segments.read_after(cut, before=self.rlog.number)

        def released(sent: int) -> None:
            self.timings.release_sent = self.clock()
            on_released(sent)

        self.streamer = ReplayStreamer(
            publisher, incarnation, backlog, self.rlog, pace, self.crashed_ns, released
        )
        self.streamer.start()

    def s4_release(self) -> dict[str, float]:
        """S4: the node is released; leave the safe state. Returns the timing breakdown."""
        self._leave_safe_state()
        self.timings.s4_done = self.clock()
        return self.timings.breakdown()

    def _leave_safe_state(self) -> None:
        """The one place a recovery releases the safe state it held at S1 (once)."""
        if self.safe_state_held:
            self.safe_state_held = False
            self.safety.release(self.node_id)

    def input_gaps(self, trustworthy: Callable[[InputGap], bool]) -> list[InputGap]:
        """Gaps in the inputs' sequence numbers seen by this recovery so far: what reached
        neither the ring nor, by the node's SWITCHED status, its live reader.

        A gap seen in the relay (after R was sealed) is held back until its topic switched,
        for at most :data:`GAP_HOLD_S`, or until the recovery stopped: only then is it known
        which of its messages the node applied from its live reader.

        Args:
            trustworthy: Whether a gap's sequence numbers are one publisher's, reliably sent
                (with two publishers they interleave; best effort loses by design).
        """
        if self.rlog is None:
            return []
        with self.rlog.cond:
            gaps = list(self.rlog.gaps)
            before_seal = self.rlog.gaps_before_seal
        found: list[InputGap] = []
        for index, gap in enumerate(gaps):
            if not trustworthy(gap):
                continue
            reported = self._reported.get(gap)
            if reported is None:
                in_relay = before_seal is not None and index >= before_seal
                if in_relay and gap.topic not in self.switched and not self._stopped:
                    since = self._held_since.setdefault(gap, self.clock())
                    if self.clock() - since < GAP_HOLD_S:
                        continue
                reported = self._reported[gap] = self._narrow(gap)
            found.extend(reported)
        return found

    def _narrow(self, gap: InputGap) -> list[InputGap]:
        """``gap`` without what the node applied from its live reader (one gap, several, or
        none)."""
        applied = sorted(s for s in self.live_only.get(gap.topic, ())
                         if gap.first <= s <= gap.last)
        if not applied:
            return [gap]
        pieces: list[InputGap] = []
        first = gap.first
        for seq in [*applied, gap.last + 1]:
            if seq > first:
                pieces.append(InputGap(gap.topic, first, seq - 1, gap.seen_after_ns,
                                       gap.publishers))
            first = seq + 1
        left = ', '.join(str(p.first) if p.first == p.last else f'{p.first}-{p.last}'
                         for p in pieces)
        _logger.info(
            '%s %s: input %s: publication seq %s, which RORY\'s reader never got, reached the '
            'node\'s live reader and were applied in order; %s', LOG_PREFIX, self.node_id,
            gap.topic, protocol.seq_ranges(applied),
            f'the input gap is {left}' if left else 'no input gap is left')
        return pieces

    def note_crash(self, died_on: InFlight | None, quarantined: Quarantined | None) -> None:
        """What a crash this recovery covers died applying (None: no message, e.g. a signal
        between callbacks), and the message it quarantined, if that crash made one poison."""
        if died_on is not None:
            self.died_on.append(died_on)
        if quarantined is not None:
            self.quarantined.append(quarantined)

    def poison_summary(self) -> dict[str, list[dict[str, Any]]]:
        """For the ``recovered`` event: ``died_on`` (per crash that died in a callback, the
        message and the process) and ``quarantined`` (the messages set aside)."""
        return {'died_on': [died_on_json(m) for m in self.died_on],
                'quarantined': [q.to_json() for q in self.quarantined]}

    def r_summary(self) -> dict[str, dict[str, int | None]]:
        """What R holds per topic (:meth:`RecoveryLog.summary`); empty without R."""
        return {} if self.rlog is None else self.rlog.summary()

    def never_delivered(self) -> dict[str, dict[str, Any]]:
        """Messages R dropped as never delivered to the node, per topic; empty without R."""
        return {} if self.rlog is None else self.rlog.never_delivered()

    def on_switched(self, topic: str, live_only: Iterable[int] = ()) -> bool:
        """A topic is live again; stop relaying it. Returns True when every topic is.

        Args:
            topic: The topic.
            live_only: Sequence numbers the node applied from its live reader that the relay
                never delivered: left out of the input gaps (:meth:`input_gaps`).
        """
        self.switched.add(topic)
        applied = set(live_only)
        if applied:
            self.live_only.setdefault(topic, set()).update(applied)
            for gap in self._reported:
                late = sorted(s for s in applied if gap.first <= s <= gap.last)
                if gap.topic == topic and late:
                    _logger.warning(
                        '%s %s: input %s: of the gap reported before the topic switched '
                        '(publication seq %d-%d), %s reached the node\'s live reader and were '
                        'applied', LOG_PREFIX, self.node_id, topic, gap.first, gap.last,
                        protocol.seq_ranges(late))
        if self.streamer is not None:
            self.streamer.switched.add(topic)
        if self.ring is not None and topic in self.ring.topics:
            self.ring.deactivate(topic)
        return self.ring is None or not self.ring.active_topics

    def finish(self) -> None:
        """The recovery is over: the handover is complete, or the node ended on its own (exit
        status 0) before it. Stop the relay, seal R, and leave the safe state if S4 has not."""
        self.stop()
        self._leave_safe_state()

    def give_up(self) -> None:
        """The node will not be started again: stop recording (R stays on disk) and make the
        ring passive. The safe state stays held: nothing will drive the robot out of it."""
        self.stop()
        if self.ring is not None:
            self.ring.deactivate()

    def stop(self) -> None:
        """Stop the relay and seal R; the safe state stays as it is (held until S4). For the
        supervisor stopping, and for a crash after S4 that starts a recovery of its own. Gaps
        held back for a switch are no longer (:meth:`input_gaps`)."""
        self._stopped = True
        if self.streamer is not None:
            self.streamer.stop()
            self.streamer = None
        if self.rlog is not None:
            self.rlog.close()


class EarlyCapture:
    """S2 early: while a running node's heartbeat is late, the ring keeps every input message.

    If the node is then killed as hung (or dies), its recovery starts from all of them
    (:meth:`take`, at the crash: :meth:`Recovery.begin`); if it beats again, it was only slow
    and the capture is dropped.
    """

    def __init__(self, node_id: str) -> None:
        self.node_id = node_id
        self.capture: Capture | None = None  # what the ring took since the beat went late

    def on_beat(self, ring: RingPort, beat: Beat) -> None:
        """The watchdog's view of the heartbeat (a running node, not recovering, that logs)."""
        if beat.late and self.capture is None:
            self.capture = Capture()
            ring.activate(self.capture)
            _logger.info('%s %s: no heartbeat for %.1f s: RORY keeps its inputs from now on',
                         LOG_PREFIX, self.node_id, beat.age_s)
        elif not beat.late and self.capture is not None:
            self.stop(ring, f'beating again ({len(self.capture)} messages kept meanwhile, '
                      'dropped)')

    def stop(self, ring: RingPort | None, why: str) -> None:
        """Drop the capture, if any, and make the ring passive again."""
        if self.capture is None:
            return
        self.capture = None
        if ring is not None:
            ring.deactivate()
        _logger.info('%s %s: input capture stopped: %s', LOG_PREFIX, self.node_id, why)

    def take(self) -> Capture | None:
        """What was captured, for the recovery of a crash; the capture ends (the ring stays
        active: the recovery's R takes over)."""
        capture, self.capture = self.capture, None
        return capture


class GapReports:
    """Says which input messages never reached this host during a node's recoveries (once
    each: the ``input_gap`` event and a warning).

    RORY cannot replay them, and a node that had not crashed would not have had them either
    (its reader was dropped too), so the recovery still ends where that node would be; but an
    operator must know that messages were lost, and why.
    """

    def __init__(self, node_id: str, events: EventSink) -> None:
        self.node_id = node_id
        self._events = events
        self.reported: set[InputGap] = set()

    def report(self, rec: Recovery) -> list[InputGap]:
        """Report the gaps of ``rec`` not reported yet; those."""
        ring = rec.ring

        def trustworthy(gap: InputGap) -> bool:
            reader = ring.topics.get(gap.topic) if ring is not None else None
            if reader is None or not reader.spec.reliable:
                return False
            publishers = gap.publishers if gap.publishers >= 0 else reader.publisher_count()
            return publishers == 1

        new = [g for g in rec.input_gaps(trustworthy) if g not in self.reported]
        for gap in new:
            self.reported.add(gap)
            _logger.warning(
                '%s %s: input %s: %d messages (publication seq %d-%d) never reached this host '
                'while the node was down, so they cannot be replayed: DDS dropped them before '
                "RORY's reader took them (a link outage longer than the DDS lease drops remote "
                'readers, and a node that had not crashed would have missed them too; or more '
                "arrived than the reader's history holds)", LOG_PREFIX, self.node_id, gap.topic,
                gap.missing, gap.first, gap.last)
            self._events.write('input_gap', self.node_id, **gap.to_json())
        return new


def say_resumed(node_id: str, folder: Path, down_since: float | None,
                events: EventSink) -> None:
    """A recovery from the store (``folder``) after a supervisor that died with the node: the
    ``resumed`` event and a warning, with how long its inputs went unrecorded (since
    ``down_since``, wall-clock seconds, if known)."""
    gap = None if down_since is None else max(0.0, time.time() - down_since)
    events.write('resumed', node_id, unrecorded_s=gap)
    _logger.warning(
        '%s %s: resuming from %s after a supervisor that did not stop cleanly%s',
        LOG_PREFIX, node_id, folder,
        '' if gap is None else f' (inputs unrecorded for up to {gap:.1f} s)',
    )


def recovery_counts(stats: ReleasedStatus) -> dict[str, int]:
    """The node's counters the ``recovered`` event carries."""
    return {'applied': stats.applied, 'replayed': stats.replayed,
            'duplicates': stats.duplicates, 'muted': stats.muted,
            'ticks_replayed': stats.ticks_replayed, 'clock_fallbacks': stats.clock_fallbacks,
            'parameter_changes_replayed': stats.parameter_changes_replayed,
            'requests_replayed': stats.requests_replayed}


def say_recovered(rec: Recovery, node_id: str, events: EventSink, gaps: GapReports, *,
                  method: Method, incarnation: int, timing: dict[str, float],
                  stats: ReleasedStatus, pace: str | None, freshness: Freshness | None,
                  gate_ms: float | None, gate_reason: str | None) -> None:
    """S4 done (``timing``: :meth:`Recovery.s4_release`): the log lines (the recovery, what the
    restore did with the key variables, input gaps, messages never delivered) and the
    ``recovered`` event."""
    gated = '' if gate_ms is None else f'; gated {gate_ms / 1000:.1f} s, {gate_reason}'
    _logger.info(
        '%s %s: recovered in %.1f ms (%s; crashes %d; replayed %s, duplicates skipped '
        '%s%s)', LOG_PREFIX, node_id, timing['total_ms'],
        ' '.join(f'{k[:-3]}={v:.1f}' for k, v in timing.items() if k != 'total_ms'),
        rec.crashes, stats.replayed, stats.duplicates, gated,
    )
    if freshness is not None and method.checkpoints:
        level = (logging.WARNING if freshness.reset or freshness.kept_stale
                 else logging.INFO)
        _logger.log(level, '%s %s: %s', LOG_PREFIX, node_id, describe_freshness(freshness))
    new_gaps = gaps.report(rec)
    never = rec.never_delivered()
    for topic, dropped in never.items():
        _logger.warning(
            '%s %s: input %s: %d message(s) (publication seq %s) reached RORY\'s reader '
            'but never the node, below what the node had of the same publisher: not '
            'replayed, to keep that publisher\'s order (a node that had not crashed '
            'never had them either)', LOG_PREFIX, node_id, topic, dropped['count'],
            dropped['seqs'])
    events.write(
        'recovered', node_id, method=method.value, crashes=rec.crashes,
        incarnation=incarnation, replay=pace, **timing, **recovery_counts(stats),
        input_gaps=[g.to_json() for g in new_gaps], r_log=rec.r_summary(),
        never_delivered=never, **rec.poison_summary(),
        freshness=None if freshness is None else freshness.to_json(),
        gate_ms=gate_ms,
        gate=gate_reason,
    )
