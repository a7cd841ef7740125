"""The environment the supervisor sets for a node it spawns, and the settings it carries: the
recovery method, how the process starts, the replay's pace and the rule for a node's id."""

from __future__ import annotations

import enum
import re
from typing import Final

# Environment the supervisor sets for a node it runs. Without ENV_NODE the runtime stays inert
# and the instrumented program behaves exactly like the original.
ENV_NODE: Final = 'RORY_NODE'
ENV_STORE: Final = 'RORY_STORE'
ENV_INCARNATION: Final = 'RORY_INCARNATION'
ENV_METHOD: Final = 'RORY_METHOD'
ENV_MODE: Final = 'RORY_MODE'
ENV_INTERVAL: Final = 'RORY_CHECKPOINT_INTERVAL'
# Set ('1') for a recovering process of a node with a release gate: it goes live but keeps its
# outputs muted until an OPEN envelope (docs/architecture.md, "The release gate").
ENV_GATED: Final = 'RORY_RELEASE_GATE'
ENV_QUARANTINE: Final = 'RORY_QUARANTINE'  # JSON [[topic, source_ns, seq], ...] to skip
# A key the supervisor draws for each run and gives its nodes through the environment, never
# over DDS: envelopes and status messages carry an HMAC of it, so another participant on the
# domain cannot feed a recovering node forged messages or steer its recovery.
ENV_SECRET: Final = 'RORY_SECRET'  # hex
# Where the node's two topics live: ``<supervisor namespace>/rory`` (see channel()).
ENV_CHANNEL: Final = 'RORY_CHANNEL'
# The supervisor's status socket (status_socket.py): statuses go to it, not over DDS.
ENV_STATUS: Final = 'RORY_STATUS_SOCKET'

# A node's id: its name in the supervisor config, its folder in the store (store.py, log.py)
# and a part of its topics' names (/rory/<node>/replay_1), so a letter, then letters, digits or
# _ (what a ROS name allows, and no path). Always used with fullmatch.
NODE_ID_RE: Final = re.compile(r'[A-Za-z][A-Za-z0-9_]*')


class Method(enum.StrEnum):
    """Recovery method; the three baselines share the supervisor with RORY."""

    RORY = 'rory'  # checkpoint + replay of the messages after its cut
    RESTART = 'restart'  # respawn with no state (what ROS's respawn does)
    CHECKPOINT = 'checkpoint'  # restore the last checkpoint, no replay
    REPLAY = 'replay'  # no checkpoints; replay every message since start

    @property
    def checkpoints(self) -> bool:
        """Whether the node takes checkpoints."""
        return self in (Method.RORY, Method.CHECKPOINT)

    @property
    def logs(self) -> bool:
        """Whether received messages are logged and replayed."""
        return self in (Method.RORY, Method.REPLAY)


class Mode(enum.StrEnum):
    """How a node process starts."""

    FRESH = 'fresh'  # first start: nothing to restore
    RECOVER = 'recover'  # restart after a crash: restore, replay, then release


class ReplayPace(enum.StrEnum):
    """How recorded messages are fed back."""

    PACED = 'paced'  # at the recorded gaps, as in the paper
    FAST = 'fast'  # as fast as the node takes them
