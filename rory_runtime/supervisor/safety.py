"""Safe-state actions: put the robot in a safe state at S1 and keep it there until S4.

The actions are shared by every supervised node: held while any node recovers, released when
the last one is back. Each action publishes its ``hold`` message once on a reliable,
transient-local topic (a latch, so a late subscriber still sees it) and, if it has a ``rate``,
again at that rate until release, for inputs that time out (a zero Twist on a velocity mux).
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass
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


class SafeState:
    """The configured safe actions and who is holding them."""

    def __init__(self, node: Node, config: SupervisorConfig) -> None:
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
            publisher = node.create_publisher(msg_class, action.topic, LATCHED_QOS)
            self._prepared.append(_Prepared(action, publisher, hold, release))
        self.holders: set[str] = set()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._rate_thread: threading.Thread | None = None

    @property
    def held(self) -> bool:
        """Whether the safe state is in force."""
        return bool(self.holders)

    def hold(self, node_id: str) -> None:
        """S1: enter the safe state on behalf of a recovering node (idempotent)."""
        with self._lock:
            first = not self.holders
            self.holders.add(node_id)
            if not first:
                return
            for p in self._prepared:
                p.publisher.publish(p.hold)
                _logger.info('%s safe state: %s held (%s)', LOG_PREFIX, p.action.topic, node_id)
            if any(p.action.rate for p in self._prepared):
                self._wake.clear()
                self._rate_thread = threading.Thread(
                    target=self._repeat, name='rory-safe-state', daemon=True
                )
                self._rate_thread.start()

    def release(self, node_id: str) -> None:
        """S4: leave the safe state once no recovering node holds it."""
        with self._lock:
            if node_id not in self.holders:
                return
            self.holders.discard(node_id)
            if self.holders:
                return
            self._wake.set()
            for p in self._prepared:
                if p.release is not None:
                    p.publisher.publish(p.release)
                _logger.info('%s safe state: %s released', LOG_PREFIX, p.action.topic)
        if self._rate_thread is not None:
            self._rate_thread.join(timeout=1.0)
            self._rate_thread = None

    def _repeat(self) -> None:
        rated = [p for p in self._prepared if p.action.rate]
        next_at = {id(p): time.monotonic() + 1.0 / float(p.action.rate or 1) for p in rated}
        while True:
            wait = max(0.0, min(next_at.values()) - time.monotonic())
            if self._wake.wait(wait):
                return
            now = time.monotonic()
            for p in rated:
                if now >= next_at[id(p)]:
                    with self._lock:
                        if not self.holders:
                            return
                        p.publisher.publish(p.hold)
                    next_at[id(p)] = now + 1.0 / float(p.action.rate or 1)
