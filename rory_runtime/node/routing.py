"""The node's input path: per topic, where its messages come from and when they are applied
(docs/architecture.md, "A message, step by step" and "The handover after release").

Each input topic is in one phase of its handover (:class:`TopicPhase`); :func:`transition`
refuses any change not in :data:`PHASE_EDGES`::

    BUFFERED -> LIVE              a fresh start, or a method without a log: live messages wait
                                  until release, then are applied in receive order
    SHADOW -> HANDOVER -> LIVE    a recovery: recorded messages come on the shadow topic; after
                                  release the supervisor relays what its ring receives until
                                  the live reader is seen to carry the same messages

A topic the node subscribes to after release starts LIVE.

The :class:`Router` holds that state and decides; the applier (applier.py) applies each
message under the runtime's lock, written ahead to the log; the output gate (gating.py) finds
what the other logged events (ticks, requests, parameter changes) name, and the applier runs
them again. A topic's subscription delivers to the router until the topic is LIVE; from then on
it delivers straight to the applier (:meth:`Applier.live_path`), so a live message runs through
one function of the runtime's, and the log writer's where the method logs.
"""

from __future__ import annotations

import enum
import inspect
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, Final, Protocol, cast

from rclpy.subscription import Subscription
from rclpy.type_support import check_for_type_support

from .. import protocol
from ..errors import RoryError
from ..msgtypes import type_name_of
from ..protocol import FLAG_RELAY, InputSpec, MessageId, Status, SwitchedStatus
from .applier import LiveCallback, Window
from .event_clock import Reading

SWITCH_CONFIRMATIONS = 3
"""Relayed messages that must also arrive live before a topic switches to its live reader."""

RELAY_SILENCE_NS = 2_000_000_000
"""Nothing from the relay for this long, neither a relayed message of any topic nor an ALIVE
(sent every ``protocol.RELAY_KEEPALIVE_S`` while it has nothing to relay), means the relay is
gone: its supervisor died. A topic whose live messages wait then switches to its live reader
rather than stall. The window still rules out duplicates; only a publisher matched late could
lose a message, which is logged."""

RELAY_WAIT_NS = 10_000_000_000
"""A topic whose live messages have waited this long while the relay is alive but relays
nothing of that topic switches to its live reader, with an error that says so.

After a link outage longer than the DDS lease the publisher matches the node's reader and the
supervisor's ring again each on its own schedule; while the ring is not matched yet the relay
has nothing of the topic to send, and waiting for it is what lets the node apply in order what
the ring brings and the supervisor report what reached neither reader. Two readers of one host
are found again within about one announcement period of each other (1 s in RORY's profile, 3 s
in Fast DDS's default): 10 s is several of either, and it bounds how long the node's view of
the topic stays behind when the ring is not matched again at all."""


class TopicPhase(enum.StrEnum):
    """Where an input topic's messages are taken from, and whether they are applied yet."""

    BUFFERED = 'BUFFERED'  # not released: live messages wait, nothing comes on the shadow topic
    SHADOW = 'SHADOW'  # recovering, not released: applied from the shadow topic; live ones wait
    HANDOVER = 'HANDOVER'  # released: applied from the relay until the live reader is confirmed
    LIVE = 'LIVE'  # applied as the live reader delivers them


P = TopicPhase
PHASE_EDGES: Final[dict[TopicPhase, frozenset[TopicPhase]]] = {
    P.BUFFERED: frozenset({P.LIVE}),
    P.SHADOW: frozenset({P.HANDOVER}),
    P.HANDOVER: frozenset({P.LIVE}),
    P.LIVE: frozenset(),
}

_FROM_SHADOW: Final = frozenset({P.SHADOW, P.HANDOVER})

# Bound once for on_live and the live-only scan, which run per message: a member read through
# its enum class goes through the enum's metaclass, a module global does not.
_HANDOVER: Final = P.HANDOVER

# Logged events other than messages: the runtime core runs them again.
_EVENT_RECORDS: Final = frozenset({protocol.TIMER_RECORD, protocol.PARAMETERS_RECORD,
                                   protocol.REQUEST_RECORD})


class IllegalPhaseChange(RuntimeError):
    """A change of a topic's phase the handover does not allow: a bug in the runtime."""


def transition(topic: str, old: TopicPhase, new: TopicPhase) -> TopicPhase:
    """``new``, if ``topic`` may go there from ``old``.

    Raises:
        IllegalPhaseChange: The edge is not in PHASE_EDGES.
    """
    if new not in PHASE_EDGES[old]:
        raise IllegalPhaseChange(f'{topic}: {old} -> {new} is not allowed')
    return new


@dataclass
class Input:
    """One subscription of the user's node."""

    sub: Subscription
    topic: str
    msg_type: type
    type_name: str
    callback: Callable[..., Any]
    with_info: bool
    user_raw: bool
    spec: InputSpec
    phase: TopicPhase
    # The subscription's callback once the topic is LIVE (Applier.live_path; made then).
    live: LiveCallback | None = None


@dataclass
class _HandoverEvidence:
    """Per-topic evidence that the live reader carries what the relay carries (after S4)."""

    live_seen: set[MessageId] = field(default_factory=set)
    relayed: deque[MessageId] = field(default_factory=lambda: deque(maxlen=64))
    # When the first live message arrived since the topic's last relayed one (0: none since).
    waiting_ns: int = 0


class Applying(Protocol):
    """What the router hands messages to (``Applier``, applier.py): it applies them under the
    runtime's lock, and holds what decides whether one is applied at all."""

    lock: threading.RLock
    # Per topic, the identities applied last (applying adds to them; a restore sets them).
    windows: dict[str, Window]
    # The counters reported to the supervisor (duplicates, replayed, quarantined, ...).
    stats: dict[str, int]
    # Poison messages the supervisor set aside: never applied again.
    quarantined: frozenset[tuple[str, MessageId]]

    def apply(self, inp: Input, raw: bytes, info: dict[str, Any], ident: MessageId,
              readings: Iterable[Reading] = (), *, log: bool) -> None:
        """Run the user's callback on one message: ``log``, a live message written ahead to
        the log; else a replayed one with its clock ``readings``."""

    def live_path(self, inp: Input) -> LiveCallback:
        """The subscription's callback for a LIVE topic: applies each message it delivers."""


def _wants_info(callback: Callable[..., Any]) -> bool:
    # The same test rclpy's Subscription.callback setter applies.
    try:
        inspect.signature(callback).bind(object())
        return False
    except TypeError:
        pass
    try:
        inspect.signature(callback).bind(object(), object())
        return True
    except TypeError:
        return False


class Router:
    """Per input topic: its phase, the live messages waiting, and the evidence for the switch.

    Args:
        recovering: Topics start on the shadow topic (a recovery with a log to replay).
        applier: Applies messages (applier.py); its windows, counters and quarantine decide
            what is skipped.
        replay_event: Runs a logged tick, request or parameter change again, with the clock
            readings it took live (``OutputGate.replay_event``).
        error: Reports an error (the runtime's ERROR status).
        status: Sends a status to the supervisor (SWITCHED).
        clock: Wall-clock nanoseconds, for the relay's silence (tests give their own).
    """

    def __init__(
        self, *, recovering: bool, applier: Applying,
        replay_event: Callable[[protocol.Msg, list[Reading]], None],
        error: Callable[[str], None], status: Callable[[Status], None],
        clock: Callable[[], int] = time.time_ns,
    ) -> None:
        self._recovering = recovering
        self.applier = applier
        self._replay_event = replay_event
        self._error = error
        self._status = status
        self.inputs: dict[str, Input] = {}
        self.pending_live: dict[str, list[tuple[MessageId, bytes, dict[str, Any]]]] = {}
        # Every identity the shadow topic delivered (applied or skipped) while its topic waits
        # for the switch. The live copies buffered meanwhile are the same messages, and far
        # more of them than the window of recent identities can hold in a long replay; this
        # set, dropped at the switch, is what keeps them from being applied twice.
        self.shadow_seen: dict[str, set[MessageId]] = {}
        self.handover: dict[str, _HandoverEvidence] = {}
        # Per topic in HANDOVER: live messages applied before a relayed one because the relay
        # will never deliver them (:meth:`_apply_live_only`), and how far its scan of
        # pending_live has come (what lies before is settled).
        self.live_only: dict[str, set[MessageId]] = {}
        self._scanned: dict[str, int] = {}
        # Shadow messages of topics the node has no subscription to yet.
        self.orphans: dict[str, list[protocol.Msg]] = {}
        self.clock = clock
        self.released_ns = 0
        # When the relay was last heard: a relayed message of any topic, or an ALIVE.
        self.relay_heard_ns = 0
        # The readings the next replayed event took when it ran live (the streamer sends an
        # event's clock records just before the event).
        self._readings: list[Reading] = []

    def phase(self, topic: str) -> TopicPhase:
        """The phase of an input topic."""
        return self.inputs[topic].phase

    def shadow_needed(self) -> bool:
        """Whether anything can still come on the shadow topic: a topic not switched to its
        live reader yet, or a relayed message waiting for a subscription the node has not
        made."""
        return bool(self.orphans) or any(
            inp.phase in _FROM_SHADOW for inp in self.inputs.values())

    # -- subscriptions ------------------------------------------------------------------------

    def adopt(self, sub: Subscription, *, released: bool) -> Input | None:
        """Take over a user subscription: raw delivery through :meth:`on_live`.

        Returns:
            Its input, None when it was adopted already.

        Raises:
            RoryError: A second subscription to the same topic, or an async callback.
        """
        topic = sub.topic_name
        if topic in self.inputs:
            if self.inputs[topic].sub is sub:
                return None
            raise RoryError(
                f'node subscribes twice to {topic}; RORY records one subscription per topic'
            )
        callback = sub.callback
        if inspect.iscoroutinefunction(callback):
            raise RoryError(f'async subscription callbacks are not supported yet ({topic})')
        msg_type = cast(type, sub.msg_type)
        check_for_type_support(msg_type)  # once: the applier deserialises without it
        type_name = type_name_of(msg_type)
        if released:
            phase = TopicPhase.LIVE
        else:
            phase = TopicPhase.SHADOW if self._recovering else TopicPhase.BUFFERED
        inp = Input(
            sub=sub,
            topic=topic,
            msg_type=msg_type,
            type_name=type_name,
            callback=callback,
            with_info=_wants_info(callback),
            user_raw=bool(sub.raw),
            spec=InputSpec.from_qos(topic, type_name, sub.qos_profile),
            phase=phase,
        )
        self.inputs[topic] = inp
        self.applier.windows.setdefault(topic, Window(protocol.window_size(inp.spec)))
        self.pending_live.setdefault(topic, [])
        sub.raw = True
        if phase is TopicPhase.LIVE:
            self._deliver_live(inp)
        else:
            on_live = self.on_live

            # A function, not a functools.partial: rclpy's executor asks
            # inspect.iscoroutinefunction of the callback at every message, which is cheapest
            # for a plain function.
            def deliver(raw: bytes, info: dict[str, Any]) -> None:
                on_live(inp, raw, info)

            sub.callback = deliver
        for msg in self.orphans.pop(topic, []):
            self.from_shadow(msg)
        return inp

    def _deliver_live(self, inp: Input) -> None:
        """The topic is LIVE: its subscription delivers straight to the applier from now on."""
        inp.live = self.applier.live_path(inp)
        inp.sub.callback = inp.live

    def _is_quarantined(self, topic: str, ident: MessageId) -> bool:
        # A poison message the supervisor set aside: never applied again, by replay or by a
        # transient-local publisher re-sending it.
        if (topic, ident) in self.applier.quarantined:
            self.applier.stats['quarantined'] += 1
            return True
        return False

    # -- the shadow topic ---------------------------------------------------------------------

    def from_shadow(self, msg: protocol.Msg) -> None:
        """A message, clock reading or other logged event from the shadow topic: replayed
        before release, relayed after."""
        if msg.topic == protocol.CLOCK_RECORD:
            self._readings.append(Reading(msg.seq, msg.source_ns, msg.recv_ns))
            return
        # What the event took when it ran live (dropped with it if it is skipped).
        readings, self._readings = self._readings, []
        if msg.topic in _EVENT_RECORDS:
            self._replay_event(msg, readings)
            return
        inp = self.inputs.get(msg.topic)
        if inp is None:
            # The subscription does not exist yet (created later by a replayed callback?).
            self.orphans.setdefault(msg.topic, []).append(msg)
            return
        if inp.phase not in _FROM_SHADOW:
            return  # already switched to its live reader, which carries this message too
        relayed = bool(msg.flags & FLAG_RELAY)
        self.shadow_seen.setdefault(msg.topic, set()).add(msg.ident)
        if relayed:
            self._note_relayed(msg.topic, msg.ident)
            self._apply_live_only(inp, msg.ident)
        if self._is_quarantined(msg.topic, msg.ident):
            pass
        elif msg.ident in self.applier.windows[msg.topic]:
            self.applier.stats['duplicates'] += 1
        else:
            info = {
                'source_timestamp': msg.source_ns,
                'received_timestamp': msg.recv_ns,
                'publication_sequence_number': msg.seq,
                'reception_sequence_number': None,
            }
            # Before release every replayed message is already in a sealed segment; relayed
            # ones are not, so the node logs them as it would a live message.
            self.applier.apply(inp, msg.data, info, msg.ident, readings, log=relayed)
            self.applier.stats['replayed'] += 1
        if relayed:
            self._maybe_switch(msg.topic)

    def relay_alive(self) -> None:
        """An ALIVE came on the shadow topic: the relay is there, with nothing to relay."""
        self.relay_heard_ns = self.clock()

    # -- live messages ------------------------------------------------------------------------

    def on_live(self, inp: Input, raw: bytes, info: dict[str, Any]) -> None:
        """A message from the topic's own subscription before the topic was LIVE: kept until
        release or the switch; applied if the topic went LIVE meanwhile (its subscription then
        delivers to the applier itself)."""
        live = inp.live
        if live is not None:
            live(raw, info)
            return
        ident = protocol.message_id(info)
        self.pending_live[inp.topic].append((ident, raw, info))
        if inp.phase is _HANDOVER:
            state = self.handover.setdefault(inp.topic, _HandoverEvidence())
            state.live_seen.add(ident)
            if not state.waiting_ns:
                state.waiting_ns = self.clock()
            self._maybe_switch(inp.topic)
            if inp.phase is _HANDOVER:
                self._switch_unconfirmed_if_stalled(inp.topic, state.waiting_ns)

    # -- release and handover (S4) ------------------------------------------------------------

    def _switch_unconfirmed_if_stalled(self, topic: str, waiting_ns: int) -> None:
        """Switch a topic in HANDOVER to its live reader without confirmation when the relay
        is gone (:data:`RELAY_SILENCE_NS`), or alive but relaying nothing of the topic while
        its live messages wait (:data:`RELAY_WAIT_NS`); with an error that says which."""
        now = self.clock()
        silent = now - max(self.released_ns, self.relay_heard_ns)
        if silent > RELAY_SILENCE_NS:
            why = (f'nothing from the supervisor\'s relay for {silent / 1e9:.1f} s, neither a '
                   'message nor an ALIVE: it is taken for gone')
        elif now - waiting_ns > RELAY_WAIT_NS:
            why = (f'the relay is alive but relayed nothing of it while its live messages '
                   f'waited {(now - waiting_ns) / 1e9:.1f} s (RORY\'s recorder not matched '
                   'with its publisher again?)')
        else:
            return
        self._error(f'no relay for {topic}; switching it to live unconfirmed: {why}'
                    f'{self._missed_before_live(topic)}')
        self.switch(topic)

    def _missed_before_live(self, topic: str) -> str:
        """What the node can tell it missed, switching ``topic`` unconfirmed: with one
        publisher, the sequence numbers between the last message applied and the first live
        one waiting that nobody applied (as words for the error; empty when none)."""
        newest = self.applier.windows[topic].newest
        if newest is None or self.inputs[topic].sub.get_publisher_count() != 1:
            return ''
        settled = self.shadow_seen.get(topic, set()) | self.live_only.get(topic, set())
        first = next((ident for ident, _, _ in self.pending_live[topic]
                      if ident not in settled and ident[1] > newest[1]), None)
        if first is None or first[1] <= newest[1] + 1:
            return ''
        low, high = newest[1] + 1, first[1] - 1
        seqs = str(low) if low == high else f'{low}-{high}'
        return f'; publication seq {seqs} never reached this node'

    def release(self) -> None:
        """S4 for the inputs: topics on the shadow topic go to HANDOVER, the others LIVE, and
        what their live readers hold is applied, in receive order (under the runtime's lock)."""
        self.released_ns = self.clock()
        for inp in self.inputs.values():
            if inp.phase is TopicPhase.BUFFERED:
                inp.phase = transition(inp.topic, inp.phase, TopicPhase.LIVE)
                self._deliver_live(inp)
            elif inp.phase is TopicPhase.SHADOW:
                inp.phase = transition(inp.topic, inp.phase, TopicPhase.HANDOVER)
        self._drain([t for t, inp in self.inputs.items() if inp.phase is TopicPhase.LIVE])

    def _drain(self, topics: list[str]) -> dict[str, list[int]]:
        """Apply what the live readers of ``topics`` hold and nobody applied yet, in receive
        order. Returns, per topic, the sequence numbers left out as passed by the relay
        (:meth:`_passed_by_relay`)."""
        passed = {topic: self._passed_by_relay(topic) for topic in topics}
        backlog = [
            (info['received_timestamp'], self.inputs[topic], ident, raw, info)
            for topic in topics
            for ident, raw, info in self.pending_live[topic]
            if ident not in passed[topic] and ident not in self.live_only.get(topic, ())
        ]
        for topic in topics:
            self.pending_live[topic] = []
        backlog.sort(key=lambda item: item[0])
        windows = self.applier.windows
        for _, inp, ident, raw, info in backlog:
            if ident in windows[inp.topic] or ident in self.shadow_seen.get(inp.topic, ()):
                self.applier.stats['duplicates'] += 1
            elif not self._is_quarantined(inp.topic, ident):
                self.applier.apply(inp, raw, info, ident, log=True)
        return {topic: sorted(ident[1] for ident in idents)
                for topic, idents in passed.items() if idents}

    def _passed_by_relay(self, topic: str) -> set[MessageId]:
        """Live messages of ``topic`` the relay skipped and can no longer deliver in order.

        The live reader and the supervisor's ring are two DDS readers on this host. After an
        outage longer than the DDS lease the publisher matches each of them again on its own
        schedule, so the live reader may hold a message the ring never got. If the relay has
        already delivered a later one of the same publisher, applying it now would apply the
        publisher's messages out of order; it is left out instead (the supervisor reports it
        inside its input gap, since its ring never logged it). The live reader's own order is
        the publisher's, so "later" is the position in its pending list. With more than one
        publisher the sequence numbers are several publishers' and positions across them mean
        nothing: those messages are applied as before.
        """
        seen = self.shadow_seen.get(topic)
        pending = self.pending_live[topic]
        if not seen or not pending or self.inputs[topic].sub.get_publisher_count() != 1:
            return set()
        last_relayed = max(
            (i for i, (ident, _, _) in enumerate(pending) if ident in seen), default=0
        )  # 0 when none was: pending[:-1] would leave out every one but the last
        window = self.applier.windows[topic]
        quarantined = self.applier.quarantined  # skipped anyway, and counted as such
        applied = self.live_only.get(topic, set())
        return {ident for ident, _, _ in pending[:last_relayed]
                if ident not in seen and ident not in window and ident not in applied
                and (topic, ident) not in quarantined}

    def _apply_live_only(self, inp: Input, relayed: MessageId) -> None:
        """Before the relayed message ``relayed``, apply the live messages of its topic that
        came before it from the same publisher and that the relay will never deliver.

        The relay sends what the ring received, in the ring's order, which is the publisher's.
        So a live message waiting with a sequence number between the last message applied and
        a relayed one, that the shadow topic has not delivered, is one the ring never received:
        after an outage longer than the DDS lease the live reader was matched again before the
        ring. Applied now, in the live reader's order, it keeps the publisher's order, and the
        node loses only what reached neither reader; the SWITCHED status names them
        (``live_only``), so that the supervisor leaves them out of the input gap it reports.

        Only with one publisher (as :meth:`_passed_by_relay`), and only between the last
        message applied and ``relayed`` in both parts of the identity (sequence number and
        source stamp): anything else waits for the switch, and what the relay passed then is
        left out there.
        """
        topic = inp.topic
        pending = self.pending_live[topic]
        start = self._scanned.get(topic, 0)
        if start >= len(pending) or inp.sub.get_publisher_count() != 1:
            return
        seen = self.shadow_seen.get(topic, set())
        window = self.applier.windows[topic]
        applied = self.live_only.setdefault(topic, set())
        quarantined = self.applier.quarantined
        with self.applier.lock:
            i = start
            while i < len(pending) and inp.phase is _HANDOVER:
                ident, raw, info = pending[i]
                if ident[1] >= relayed[1]:
                    break  # the live reader is ahead of the relay: it will deliver this
                newest = window.newest
                between = ident[0] <= relayed[0] and (
                    newest is None or (ident[1] > newest[1] and ident[0] >= newest[0]))
                if (between and ident not in seen and ident not in window
                        and ident not in applied and (topic, ident) not in quarantined):
                    self.applier.apply(inp, raw, info, ident, log=True)
                    applied.add(ident)
                # Anything else is settled: delivered, applied, or not between the two (left
                # to the switch).
                i += 1
            self._scanned[topic] = i

    def _note_relayed(self, topic: str, ident: MessageId) -> None:
        state = self.handover.setdefault(topic, _HandoverEvidence())
        state.relayed.append(ident)
        state.waiting_ns = 0
        self.relay_heard_ns = self.clock()

    def _maybe_switch(self, topic: str) -> None:
        """Switch a topic to its live reader once that reader is seen to carry the relay.

        Evidence: SWITCH_CONFIRMATIONS relayed messages also arrived live, the latest relayed
        one among them. Publishers deliver reliably and in order, so from that message on the
        live reader has everything and the relay has delivered everything before it.
        """
        state = self.handover.get(topic)
        if (state is None or not state.relayed
                or self.inputs[topic].phase is not TopicPhase.HANDOVER):
            return
        confirmed = sum(1 for ident in state.relayed if ident in state.live_seen)
        if confirmed < SWITCH_CONFIRMATIONS or state.relayed[-1] not in state.live_seen:
            return
        self.switch(topic)

    def switch(self, topic: str) -> None:
        """Take ``topic`` from its live reader from now on (HANDOVER -> LIVE).

        Raises:
            IllegalPhaseChange: The topic is not in HANDOVER.
        """
        inp = self.inputs[topic]
        with self.applier.lock:
            inp.phase = transition(topic, inp.phase, TopicPhase.LIVE)
            self._deliver_live(inp)
            passed = self._drain([topic]).get(topic, [])
            self.shadow_seen.pop(topic, None)
            live_only = sorted(ident[1] for ident in self.live_only.pop(topic, ()))
            self._scanned.pop(topic, None)
        self.handover.pop(topic, None)
        if passed:
            self.applier.stats['passed_by_relay'] += len(passed)
            seqs = protocol.seq_ranges(passed)
            self._error(
                f'{topic}: {len(passed)} message(s) (publication seq {seqs}) '
                'reached only the live reader, after the relay had delivered later ones from '
                'the same publisher: not applied, to keep its order (RORY\'s recorder never '
                'got them; see the input gap)'
            )
        self._status(SwitchedStatus(topic=topic, passed_by_relay=tuple(passed),
                                    live_only=tuple(live_only)))
