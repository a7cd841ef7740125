"""The node side of RORY: what an instrumented node links against.

``rory-instrument`` decorates a node class with :func:`checkpointed`. Run without the supervisor
the decorator returns the class untouched, so the program behaves exactly like the original.
Under the supervisor (``RORY_NODE`` set) it attaches a :class:`NodeRuntime` to every instance,
which sits between the node and rclpy:

* every subscription is switched to raw delivery so the runtime sees the CDR bytes; it logs each
  message to the current MCAP segment *before* handing the deserialized message to the user's
  callback (write-ahead), and keeps a window of recent message identities per topic;
* every user callback runs under one lock, and the checkpoint timer takes the same lock, so a
  snapshot is always taken between two callbacks;
* while the node is isolated (S2), publishers are muted, user timers are held and live messages
  are buffered instead of applied; recorded messages arrive on the node's shadow topic instead.

Recovery from the node's point of view (the supervisor drives S1-S4, see
``supervisor/recovery.py``):

1. restore: before any user callback can run, the newest valid checkpoint is loaded from the store
   (S3, restore);
2. the node says HELLO and answers SYNC, proving the shadow path works both ways;
3. recorded messages after the checkpoint's cut are applied in recorded order (S3, replay);
   anything whose identity is already in the window was absorbed before and is skipped;
4. RELEASE: outputs unmuted, timers started (S4). Each input topic is still taken from the
   shadow topic, where the supervisor relays what its own reader receives, until the node's live
   subscription has been seen to carry the same messages; then that topic switches to live
   (routing.py).
   The relay covers messages published before the new live reader was matched by its writer,
   which a plain re-subscribe would silently lose.

Where each part lives: patching.py (the decorator and what it patches), runtime.py
(:class:`NodeRuntime`: the lock, adoption, restore, applying, reporting), routing.py (each
input topic's path and its handover), checkpointer.py (checkpoints and the log segments they
cut). This module is the node side's front door: ``rory_runtime.checkpointed`` and code written
against earlier versions import these names from here.
"""

from __future__ import annotations

from .patching import checkpoint_module, checkpointed
from .runtime import NodeRuntime, RuntimeEnv
from .state import CheckpointSpec

__all__ = ['CheckpointSpec', 'NodeRuntime', 'RuntimeEnv', 'checkpoint_module', 'checkpointed']
