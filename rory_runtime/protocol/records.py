"""Records in a node's log segments that are not messages of an input topic."""

from __future__ import annotations

import struct
from typing import Final

from .envelopes import CDR_LE

# Records in a node's log segments that are not messages: a tick of one of its timers, a
# clock reading taken inside one of its callbacks, a parameter change, a service request
# (docs/architecture.md, "Timers and the clock"). No DDS topic has these names (':' is not
# allowed in a ROS name); they exist only in segments and on the shadow topic.
TIMER_RECORD: Final = '/rory:timer'
CLOCK_RECORD: Final = '/rory:clock'
EVENT_RECORD_TYPE: Final = 'builtin_interfaces/msg/Time'
# A change of the node's parameters from outside, as a serialized
# rcl_interfaces/msg/ParameterEvent (docs/architecture.md, "Parameters").
PARAMETERS_RECORD: Final = '/rory:parameters'
# A request to one of the node's services, by creation order (docs/architecture.md, "Services").
REQUEST_RECORD: Final = '/rory:request'


def pack_time_record(ns: int) -> bytes:
    """The CDR bytes of an event record: the time it carries as a ``builtin_interfaces/Time``
    (what a bag reader shows; RORY reads the record's timestamps)."""
    sec, nanosec = divmod(max(ns, 0), 1_000_000_000)
    return CDR_LE + struct.pack('<iI', min(sec, 2**31 - 1), nanosec)


def is_input_topic(topic: str) -> bool:
    """Whether a logged record is a message of an input topic (not a tick or clock reading)."""
    return topic not in (TIMER_RECORD, CLOCK_RECORD, PARAMETERS_RECORD, REQUEST_RECORD)
