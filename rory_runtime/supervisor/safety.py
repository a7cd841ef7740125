"""Safe-state actions: put the robot in a safe state at S1 and keep it there until S4.

The actions are shared by every supervised node: held while any node recovers, released when
the last one is back; an action may be scoped to some nodes (``nodes: [...]``), e.g. one robot's
stop when one supervisor runs two robots. Each action publishes its ``hold`` message once on a
reliable, transient-local topic (a latch, so a late subscriber still sees it) and, if it has a
``rate``, again at that rate until release, for inputs that time out (a zero Twist on a velocity
mux).
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..errors import ConfigError
from ..msgtypes import MessageTypeError, build_message, get_message_class
from .config import SafeAction, SupervisorConfig
from .states import LOG_PREFIX

_logger = logging.getLogger('rory.supervisor')

LATCHED_QOS = QoSProfile(
    history=HistoryPolicy.KEEP_LAST,
    depth=1,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


@dataclass
class _Prepared:
    action: SafeAction
    publisher: Publisher
    hold: Any
    release: Any | None
    holders: set[str] = field(default_factory=set)  # recovering nodes in its scope

    def covers(self, node_id: str) -> bool:
        return self.action.nodes is None or node_id in self.action.nodes


class SafeState:
    """The configured safe actions and who is holding each.

    An action without ``nodes`` is held while any node recovers; one with ``nodes`` only while
    one of those does (a supervisor that runs two robots stops only the robot that crashed).
    """

    def __init__(self, node: Node, config: SupervisorConfig,
                 notify: Callable[[str, str, str], None] | None = None) -> None:
        # notify(node_id, 'held' | 'released', topic): e.g. a record in events.jsonl.
        self._notify = notify or (lambda _node, _what, _topic: None)
        self._prepared: list[_Prepared] = []
        for i, action in enumerate(config.safe_state):
            where = f'safe_state[{i}]'
            try:
                msg_class = get_message_class(action.msgtype)
                hold = build_message(action.msgtype, action.hold, where=f'{where}.hold')
                release = (
                    None
                    if action.release is None
                    else build_message(action.msgtype, action.release, where=f'{where}.release')
                )
            except MessageTypeError as err:
                raise ConfigError(config.path, where, str(err)) from None
            # Created at start-up so subscribers have long discovered them when a crash comes.
            # A relative topic resolves in the supervisor's namespace (one robot's e-stop).
            publisher = node.create_publisher(msg_class, action.topic, LATCHED_QOS)
            self._prepared.append(_Prepared(action, publisher, hold, release))
        self._lock = threading.Lock()
        # The thread that republishes rated holds, and the event that ends it (one per thread,
        # so a hold right after a release never revives the thread being stopped).
        self._rate_thread: tuple[threading.Thread, threading.Event] | None = None

    @property
    def holders(self) -> set[str]:
        """The recovering nodes that hold some action."""
        with self._lock:
            return set().union(*(p.holders for p in self._prepared))

    @property
    def held(self) -> bool:
        """Whether any safe action is in force."""
        return bool(self.holders)

    def held_topics(self) -> list[str]:
        """The resolved topics of the actions in force."""
        with self._lock:
            return [p.publisher.topic_name for p in self._prepared if p.holders]

    def hold(self, node_id: str) -> None:
        """S1: enter the safe state on behalf of a recovering node (idempotent)."""
        with self._lock:
            for p in self._prepared:
                if not p.covers(node_id) or node_id in p.holders:
                    continue
                p.holders.add(node_id)
                if len(p.holders) == 1:
                    p.publisher.publish(p.hold)
                    _logger.info('%s safe state: %s held (%s)', LOG_PREFIX,
                                 p.publisher.topic_name, node_id)
                    self._notify(node_id, 'held', p.publisher.topic_name)
            rated = any(p.action.rate and p.holders for p in self._prepared)
            if rated and self._rate_thread is None:
                done = threading.Event()
                thread = threading.Thread(
                    target=self._repeat, args=(done,), name='rory-safe-state', daemon=True
                )
                self._rate_thread = (thread, done)
                thread.start()

    def release(self, node_id: str) -> None:
        """S4: leave each action once no recovering node in its scope holds it."""
        with self._lock:
            for p in self._prepared:
                if node_id not in p.holders:
                    continue
                p.holders.discard(node_id)
                if p.holders:
                    continue
                if p.release is not None:
                    p.publisher.publish(p.release)
                _logger.info('%s safe state: %s released', LOG_PREFIX, p.publisher.topic_name)
                self._notify(node_id, 'released', p.publisher.topic_name)
            stopping = None
            if self._rate_thread is not None and not any(
                p.action.rate and p.holders for p in self._prepared
            ):
                stopping, self._rate_thread = self._rate_thread, None
                stopping[1].set()
        if stopping is not None:
            stopping[0].join(timeout=1.0)

    def _repeat(self, done: threading.Event) -> None:
        rated = [p for p in self._prepared if p.action.rate]
        next_at = {id(p): time.monotonic() + 1.0 / float(p.action.rate or 1) for p in rated}
        while True:
            wait = max(0.0, min(next_at.values()) - time.monotonic())
            if done.wait(wait):
                return
            now = time.monotonic()
            for p in rated:
                if now >= next_at[id(p)]:
                    with self._lock:
                        if p.holders:
                            p.publisher.publish(p.hold)
                    next_at[id(p)] = now + 1.0 / float(p.action.rate or 1)
