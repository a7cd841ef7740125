"""A node's inputs as the supervisor mirrors them (the ring), and a message's identity."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Final, Protocol

from ..errors import ProtocolError

# Publisher sequence numbers are stored in MCAP's u32 ``sequence`` field; identities use the
# same truncation everywhere so that a live message and its logged copy compare equal.
SEQ_MASK: Final = 0xFFFFFFFF

MessageId = tuple[int, int]
"""A message's identity: (publisher source timestamp ns, publisher sequence number & SEQ_MASK)."""


def seq_ranges(numbers: Iterable[int], sep: str = ', ') -> str:
    """Sequence numbers as runs: ``[4, 5, 6, 9]`` is ``4-6, 9``."""
    spans: list[list[int]] = []
    for n in numbers:
        if spans and n == spans[-1][1] + 1:
            spans[-1][1] = n
        else:
            spans.append([n, n])
    return sep.join(str(a) if a == b else f'{a}-{b}' for a, b in spans)


def message_id(info: dict[str, Any]) -> MessageId:
    """Identity of a received message from rclpy's message info."""
    return (int(info['source_timestamp']), int(info['publication_sequence_number']) & SEQ_MASK)


# Describing a node's inputs, so the supervisor can hold matching readers (the ring).


class QosProfileLike(Protocol):
    """What :meth:`InputSpec.from_qos` reads of an rclpy ``QoSProfile``: named by its shape, so
    that the protocol neither loads nor type-checks with rclpy."""

    @property
    def history(self) -> object: ...

    @property
    def reliability(self) -> object: ...

    @property
    def durability(self) -> object: ...

    @property
    def depth(self) -> int: ...


@dataclass(frozen=True)
class InputSpec:
    """One subscription of a supervised node, as the supervisor needs to mirror it."""

    topic: str
    msgtype: str  # 'pkg/msg/Name'
    reliable: bool
    transient_local: bool
    depth: int  # 0 for keep-all

    def to_json(self) -> dict[str, Any]:
        """Plain dict for a status message."""
        return {
            'topic': self.topic,
            'type': self.msgtype,
            'reliable': self.reliable,
            'transient_local': self.transient_local,
            'depth': self.depth,
        }

    @classmethod
    def from_json(cls, obj: Any) -> InputSpec:
        """Parse the dict form.

        Raises:
            ProtocolError: Missing or ill-typed fields.
        """
        expected = {
            'topic': str, 'type': str, 'reliable': bool, 'transient_local': bool, 'depth': int,
        }
        if not isinstance(obj, dict):
            raise ProtocolError(f'bad input description {obj!r}: not an object')
        for key, kind in expected.items():
            value = obj.get(key)
            # bool is an int in Python; a depth of True is not a depth
            if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
                raise ProtocolError(f'bad input description {obj!r}: {key} must be {kind.__name__}')
        if obj['depth'] < 0:
            raise ProtocolError(f'bad input description {obj!r}: depth must be >= 0')
        return cls(
            topic=obj['topic'],
            msgtype=obj['type'],
            reliable=obj['reliable'],
            transient_local=obj['transient_local'],
            depth=obj['depth'],
        )

    @classmethod
    def from_qos(cls, topic: str, msgtype: str, qos: QosProfileLike) -> InputSpec:
        """Describe a subscription from its QoS profile (an rclpy ``QoSProfile``)."""
        # Here, not at the top: the protocol loads no rclpy (the node's side, which calls this,
        # has it loaded already).
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

        keep_all = qos.history == HistoryPolicy.KEEP_ALL
        return cls(
            topic=topic,
            msgtype=msgtype,
            reliable=qos.reliability != ReliabilityPolicy.BEST_EFFORT,
            transient_local=qos.durability == DurabilityPolicy.TRANSIENT_LOCAL,
            depth=0 if keep_all else int(qos.depth),
        )


def ring_depth(spec: InputSpec) -> int:
    """How many recent messages of an input the supervisor's passive reader holds.

    A crashed node can have left at most its own queue depth of received-but-unapplied
    messages; the margin covers what arrives between the crash and the supervisor noticing.
    """
    return (spec.depth if spec.depth else 256) + 16


def window_size(spec: InputSpec) -> int:
    """How many applied message identities the node remembers per input.

    Must exceed :func:`ring_depth`: everything the ring hands back after a crash is then
    either in the node's window (absorbed, skipped) or new.
    """
    return ring_depth(spec) + 64
