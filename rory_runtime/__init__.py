"""rory_runtime: what an instrumented ROS 2 node links against, and the supervisor.

``rory-instrument`` adds ``import rory_runtime`` and ``@rory_runtime.checkpointed(...)`` (or, for
a node written as functions, ``rory_runtime.checkpoint_module(...)``) to a node's source.
Unsupervised, both do nothing and import nothing more, so the program behaves (and starts)
exactly like the original.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, TypeVar

from .protocol import ENV_NODE

__all__ = ['checkpoint_module', 'checkpointed', 'supervise']

C = TypeVar('C', bound=type)


def checkpointed(
    *,
    vars: tuple[str, ...],
    manifest: str,
    module_vars: tuple[str, ...] = (),
    checkpoint_interval: float | None = None,
    replay: str | None = None,
    freshness: tuple[tuple[str, float, str], ...] = (),
) -> Callable[[C], C]:
    """Mark a node class's key variables for checkpointing (see :mod:`rory_runtime.node.attach`)."""
    if not os.environ.get(ENV_NODE):
        return lambda cls: cls
    from .node.attach import checkpointed as attach_checkpointed

    return attach_checkpointed(
        vars=vars,
        manifest=manifest,
        module_vars=module_vars,
        checkpoint_interval=checkpoint_interval,
        replay=replay,
        freshness=freshness,
    )


def checkpoint_module(
    module: str,
    *,
    vars: tuple[str, ...],
    manifest: str,
    checkpoint_interval: float | None = None,
    replay: str | None = None,
    freshness: tuple[tuple[str, float, str], ...] = (),
) -> None:
    """Mark a function-style node's module globals as its state (see :mod:`.node.attach`)."""
    if not os.environ.get(ENV_NODE):
        return
    from .node.attach import checkpoint_module as attach_checkpoint_module

    attach_checkpoint_module(
        module,
        vars=vars,
        manifest=manifest,
        checkpoint_interval=checkpoint_interval,
        replay=replay,
        freshness=freshness,
    )


def supervise(config: Any, **options: Any) -> int:
    """Run a supervisor from a program, as ``rory supervise`` does; see
    :func:`rory_runtime.supervisor.embed.supervise` (imported only when called)."""
    from .supervisor.embed import supervise as embedded_supervise

    return embedded_supervise(config, **options)
