"""Everything the node-side runtime and the supervisor agree on, in one place.

The two halves of RORY meet only here, a module per concern:

- ``env``: the environment variables the supervisor sets for a node it spawns, and the settings
  they carry (``Method``, ``Mode``, ``ReplayPace``, the rule for a node's id);
- ``topics``: the name and QoS of the topic the supervisor answers on, the node's shadow topic;
- ``envelopes``: the binary envelopes it sends there (their layout: that module's docstring);
- ``statuses``: the status messages a node sends, as datagrams on the supervisor's status
  socket, one frozen class per kind, ``encode_status`` / ``decode_status``;
- ``inputs``: a node's inputs as the supervisor mirrors them (``InputSpec``, ``ring_depth``,
  ``window_size``) and a message's identity (``MessageId``, ``SEQ_MASK``);
- ``records``: the records of a node's log segments that are not messages (ticks, clock
  readings, parameter changes, service requests);
- ``signing``: the HMAC tag envelopes and statuses carry.

Their public names are re-exported here (``from rory_runtime.protocol import ...``). Loading the
package loads no rclpy: the shadow topic's QoS (``REPLAY_QOS``) is made when first read, so that
a module reading statuses or envelopes (the supervisor's decisions) runs without ROS.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from . import topics
from .env import (
    ENV_CHANNEL,
    ENV_GATED,
    ENV_INCARNATION,
    ENV_INTERVAL,
    ENV_METHOD,
    ENV_MODE,
    ENV_NODE,
    ENV_QUARANTINE,
    ENV_SECRET,
    ENV_STATUS,
    ENV_STORE,
    NODE_ID_RE,
    Method,
    Mode,
    ReplayPace,
)
from .envelopes import (
    FLAG_RELAY,
    RELAY_KEEPALIVE_S,
    Alive,
    Envelope,
    EnvelopeKind,
    Msg,
    Open,
    Release,
    SignedPublisher,
    Sync,
    pack_alive,
    pack_msg,
    pack_open,
    pack_release,
    pack_sync,
    sign,
    unpack,
)
from .inputs import (
    SEQ_MASK,
    InputSpec,
    MessageId,
    message_id,
    ring_depth,
    seq_ranges,
    window_size,
)
from .records import (
    CLOCK_RECORD,
    EVENT_RECORD_TYPE,
    PARAMETERS_RECORD,
    REQUEST_RECORD,
    TIMER_RECORD,
    is_input_topic,
    pack_time_record,
)
from .signing import TAG_BYTES
from .statuses import (
    CheckpointFailure,
    CheckpointStatus,
    ErrorStatus,
    HelloStatus,
    InputsStatus,
    OpenedStatus,
    ReleasedStatus,
    RestoredCheckpoint,
    Status,
    StatusKind,
    StatusMessage,
    SwitchedStatus,
    SyncedStatus,
    decode_status,
    encode_status,
)
from .topics import (
    DEFAULT_CHANNEL,
    channel,
    replay_topic,
)

if TYPE_CHECKING:
    from .topics import REPLAY_QOS
else:
    # Hidden from mypy, which would take every unknown name of the package for an attribute.
    def __getattr__(name: str) -> Any:
        """``REPLAY_QOS``, an rclpy ``QoSProfile``: rclpy is loaded when it is first read."""
        if name == 'REPLAY_QOS':
            return topics.REPLAY_QOS
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')


__all__ = [
    'CLOCK_RECORD',
    'DEFAULT_CHANNEL',
    'ENV_CHANNEL',
    'ENV_GATED',
    'ENV_INCARNATION',
    'ENV_INTERVAL',
    'ENV_METHOD',
    'ENV_MODE',
    'ENV_NODE',
    'ENV_QUARANTINE',
    'ENV_SECRET',
    'ENV_STATUS',
    'ENV_STORE',
    'EVENT_RECORD_TYPE',
    'FLAG_RELAY',
    'NODE_ID_RE',
    'PARAMETERS_RECORD',
    'RELAY_KEEPALIVE_S',
    'REPLAY_QOS',
    'REQUEST_RECORD',
    'SEQ_MASK',
    'TAG_BYTES',
    'TIMER_RECORD',
    'Alive',
    'CheckpointFailure',
    'CheckpointStatus',
    'Envelope',
    'EnvelopeKind',
    'ErrorStatus',
    'HelloStatus',
    'InputSpec',
    'InputsStatus',
    'MessageId',
    'Method',
    'Mode',
    'Msg',
    'Open',
    'OpenedStatus',
    'Release',
    'ReleasedStatus',
    'ReplayPace',
    'RestoredCheckpoint',
    'SignedPublisher',
    'Status',
    'StatusKind',
    'StatusMessage',
    'SwitchedStatus',
    'Sync',
    'SyncedStatus',
    'channel',
    'decode_status',
    'encode_status',
    'is_input_topic',
    'message_id',
    'pack_alive',
    'pack_msg',
    'pack_open',
    'pack_release',
    'pack_sync',
    'pack_time_record',
    'replay_topic',
    'ring_depth',
    'seq_ranges',
    'sign',
    'unpack',
    'window_size',
]
