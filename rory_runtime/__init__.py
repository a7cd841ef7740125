"""rory_runtime: what an instrumented ROS 2 node links against, and the supervisor.

``rory-instrument`` adds ``import rory_runtime`` and ``@rory_runtime.checkpointed(...)`` to a
node's source. Unsupervised, the decorator returns the class untouched without importing the
runtime, so the program behaves (and starts) exactly like the original.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import TypeVar

from .protocol import ENV_NODE

__all__ = ['checkpoint_module', 'checkpointed']

C = TypeVar('C', bound=type)


def checkpointed(*, vars: tuple[str, ...], manifest: str) -> Callable[[C], C]:
    """Mark a node class's key variables for checkpointing (see :mod:`rory_runtime.attach`)."""
    if not os.environ.get(ENV_NODE):
        return lambda cls: cls
    from .attach import checkpointed as attach_checkpointed

    return attach_checkpointed(vars=vars, manifest=manifest)
