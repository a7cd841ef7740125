"""Stand-ins for the rclpy entities the node runtime adopts, and the messages a test feeds it:
the runtime's bookkeeping driven by hand with real CDR bytes and a real store, and no DDS
participant. The same paths run for real in tests/integration.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.clock import Clock
from rclpy.qos import QoSProfile
from rclpy.serialization import serialize_message
from std_msgs.msg import Int64

from rory_runtime import protocol
from rory_runtime.node.runtime import NodeRuntime, RuntimeEnv
from rory_runtime.node.state import CheckpointSpec
from rory_runtime.protocol import FLAG_RELAY, Method, Mode


@dataclass
class FakeSubscription:
    """What adopt_subscription reads from an rclpy Subscription."""

    topic_name: str
    callback: Callable[..., Any]
    msg_type: type = Int64
    raw: bool = False
    qos_profile: QoSProfile = field(default_factory=lambda: QoSProfile(depth=10))

    def get_publisher_count(self) -> int:
        return 1


class FakeTimer:
    """What adopt_timer, a tick and a release read from an rclpy Timer: rcl's schedule on
    ``clock``, its next call a period after a reset (an exchange of the period leaves it). A
    period set calls the hook NodeTimers put on the timer, as node_timers.install makes
    rclpy's ``timer_period_ns`` setter do."""

    def __init__(self, callback: Callable[[], Any], clock: Clock,
                 timer_period_ns: int = 1_000_000_000) -> None:
        self.callback = callback
        self.clock = clock
        self.canceled = False
        self.next_call_ns = 0
        self.destroyed = False
        self._period_ns = timer_period_ns

    @property
    def timer_period_ns(self) -> int:
        return self._period_ns

    @timer_period_ns.setter
    def timer_period_ns(self, value: int) -> None:
        old, self._period_ns = self._period_ns, int(value)
        hook = self.__dict__.get('_rory_period_changed')
        if hook is not None:
            hook(old, int(value))

    def is_canceled(self) -> bool:
        return self.canceled

    def cancel(self) -> None:
        self.canceled = True

    def reset(self) -> None:
        self.canceled = False
        self.next_call_ns = int(self.clock.now().nanoseconds) + self.timer_period_ns

    def destroy(self) -> None:
        self.destroyed = True

    def time_until_next_call(self) -> int:
        return self.next_call_ns - int(self.clock.now().nanoseconds)


def make_runtime(tmp_path: Path, mode: Mode, method: Method = Method.RORY,
                 incarnation: int = 2) -> NodeRuntime:
    """A runtime of node ``n`` whose key variable is ``x``, its store in ``tmp_path``."""
    env = RuntimeEnv(node_id='n', store=tmp_path, incarnation=incarnation, method=method,
                     mode=mode, interval=2.0)
    return NodeRuntime(CheckpointSpec(('x',), 'sha256:0'), env)


def info(n: int) -> dict[str, Any]:
    """The message info of message ``n``: its identity (source timestamp, sequence) is (n, n)."""
    return {
        'source_timestamp': n,
        'received_timestamp': 1_000 + n,
        'publication_sequence_number': n,
        'reception_sequence_number': None,
    }


def cdr(n: int) -> bytes:
    """Message ``n`` of /numbers, serialized."""
    return bytes(serialize_message(Int64(data=n)))


def shadow(n: int, *, relay: bool = False) -> protocol.Msg:
    """Message ``n`` of /numbers as the shadow topic carries it (replayed, or relayed)."""
    return protocol.Msg(
        incarnation=2, flags=FLAG_RELAY if relay else 0, recv_ns=1_000 + n, source_ns=n, seq=n,
        topic='/numbers', data=cdr(n),
    )


def adopt_numbers(rt: NodeRuntime, applied: list[int]) -> FakeSubscription:
    """A subscription to /numbers whose callback appends each message's number to ``applied``."""
    sub = FakeSubscription('/numbers', lambda msg: applied.append(msg.data))
    rt.adopt_subscription(sub)  # type: ignore[arg-type]
    return sub


def deliver_live(sub: FakeSubscription, n: int) -> None:
    """Message ``n`` arrives on the subscription (raw delivery, as the executor does)."""
    sub.callback(cdr(n), info(n))
