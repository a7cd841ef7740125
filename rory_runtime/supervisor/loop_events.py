"""The supervisor's main loop's events: what its threads (a process's reaper, the status
inbox, a replay streamer, a service call, a signal) post to its queue; all handled on the main
thread, one at a time."""

from __future__ import annotations

import queue
from dataclasses import dataclass

from ..protocol import StatusMessage


@dataclass(frozen=True)
class ChildExited:
    node: str
    incarnation: int
    code: int
    at: float  # monotonic, taken by the reaper the moment waitpid returned
    at_ns: int


@dataclass(frozen=True)
class StatusReceived:
    node: str
    message: StatusMessage


@dataclass(frozen=True)
class Released:
    node: str
    incarnation: int
    sent: int


@dataclass(frozen=True)
class Stop:
    reason: str


@dataclass(frozen=True)
class GateCall:
    """A call on a node's release gate service; the answer goes back through ``reply``."""

    node: str
    reply: queue.Queue[tuple[bool, str]]


Event = ChildExited | StatusReceived | Released | Stop | GateCall

GATE_CALL_ANSWER = 2.0
"""Seconds a release call waits for the main loop's answer (it is busy for milliseconds)."""


def ask_gate(events: queue.SimpleQueue[Event], node: str,
             timeout: float = GATE_CALL_ANSWER) -> tuple[bool, str]:
    """A call on ``node``'s release gate, from the thread that serves it (the ROS spinner's):
    the main loop owns the node's state and answers (``ManagedNode.on_gate_call``)."""
    reply: queue.Queue[tuple[bool, str]] = queue.Queue(maxsize=1)
    events.put(GateCall(node, reply))
    try:
        return reply.get(timeout=timeout)
    except queue.Empty:
        return False, 'the supervisor did not answer'
