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

This module patches the node class (the decorator, its ``__init__`` and entity factories); the
runtime it attaches is runtime.py's, its input path routing.py's and its checkpoints
checkpointer.py's.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any, TypeVar

from rclpy.node import Node

from .freshness import rules_from
from .runtime import NodeRuntime, RuntimeEnv
from .state import CheckpointSpec

# Imported from here by earlier code (rory_runtime/__init__.py, tests, benches): the core's
# names stay reachable as rory_runtime.attach.<name>.
__all__ = ['CheckpointSpec', 'NodeRuntime', 'RuntimeEnv', 'checkpoint_module', 'checkpointed']

N = TypeVar('N', bound=type[Node])


def checkpointed(
    *,
    vars: tuple[str, ...],
    manifest: str,
    module_vars: tuple[str, ...] = (),
    checkpoint_interval: float | None = None,
    replay: str | None = None,
    freshness: tuple[tuple[str, float, str], ...] = (),
) -> Callable[[N], N]:
    """Class decorator that ``rory-instrument`` puts on a node class.

    Args:
        vars: Paths of the ``self.<path>`` attributes that make up the node's state.
        manifest: Hash of the instrumented code version; a checkpoint written under another
            manifest is refused.
        module_vars: Paths of module globals that are state too.
        checkpoint_interval: Seconds between checkpoints, unless the supervisor sets it.
        replay: 'paced' or 'fast', unless the supervisor sets it.
        freshness: ``(key, max_age, on_stale)`` per variable with a rule (freshness.py).

    Returns:
        The decorator. Unsupervised, it returns the class unchanged.
    """

    def decorate(cls: N) -> N:
        env = RuntimeEnv.from_environ()
        if env is None:
            return cls
        spec = CheckpointSpec(
            tuple(vars), manifest, tuple(module_vars), cls.__module__, checkpoint_interval, replay,
            rules_from(freshness),
        )
        _install(cls, spec, env)
        return cls

    return decorate


def checkpoint_module(
    module: str,
    *,
    vars: tuple[str, ...],
    manifest: str,
    checkpoint_interval: float | None = None,
    replay: str | None = None,
    freshness: tuple[tuple[str, float, str], ...] = (),
) -> None:
    """For nodes written as functions: the module's globals ``vars`` are the node's state.

    The runtime attaches to the first rclpy Node this process creates after the call (what
    ``rclpy.create_node`` returns in such a module). Unsupervised, it does nothing.
    """
    env = RuntimeEnv.from_environ()
    if env is None:
        return
    spec = CheckpointSpec((), manifest, tuple(vars), module, checkpoint_interval, replay,
                          rules_from(freshness))
    _watch_for_node(spec, env)



# ---------------------------------------------------------------------------------------------
# Class patching. Only the entity factories and __init__ are wrapped; the rest of the class is
# left alone.


def _install(cls: type[Node], spec: CheckpointSpec, env: RuntimeEnv) -> None:
    if cls.__dict__.get('__rory_installed__'):
        return
    cls.__rory_spec__ = spec  # type: ignore[attr-defined]
    cls.__rory_installed__ = True  # type: ignore[attr-defined]
    original_init = cls.__init__

    @functools.wraps(original_init)
    def __init__(self: Node, *args: Any, **kwargs: Any) -> None:
        runtime = NodeRuntime.of(self, env)
        runtime.init_depth += 1
        try:
            original_init(self, *args, **kwargs)
        finally:
            runtime.init_depth -= 1
        if runtime.init_depth == 0:
            # Construction is over (also for subclasses that call our __init__ via super()).
            runtime.on_constructed(self)

    cls.__init__ = __init__  # type: ignore[method-assign]

    for name, adopt in _factories():
        setattr(cls, name, _wrap_factory(getattr(cls, name), adopt, env))


def _watch_for_node(spec: CheckpointSpec, env: RuntimeEnv) -> None:
    """Attach a runtime to the next Node constructed in this process."""
    original_init = Node.__init__
    if getattr(original_init, '__rory_watch__', None) is not None:
        return  # one function-style node per process

    @functools.wraps(original_init)
    def __init__(self: Node, *args: Any, **kwargs: Any) -> None:
        original_init(self, *args, **kwargs)
        if type(self).__dict__.get('__rory_installed__') or '_rory_runtime' in self.__dict__:
            return  # an instrumented class has its own runtime
        Node.__init__ = original_init  # type: ignore[method-assign]
        runtime = NodeRuntime(spec, env)
        self.__dict__['_rory_runtime'] = runtime
        for name, adopt in _factories():
            bound = getattr(self, name)
            setattr(self, name, _wrap_factory(bound, adopt, env, bound_method=True))
        runtime.on_constructed(self)

    __init__.__rory_watch__ = spec  # type: ignore[attr-defined]
    Node.__init__ = __init__  # type: ignore[method-assign]


def _factories() -> tuple[tuple[str, Callable[[NodeRuntime, Any], None]], ...]:
    return (
        ('create_subscription', NodeRuntime.adopt_subscription),
        ('create_publisher', NodeRuntime.adopt_publisher),
        ('create_timer', NodeRuntime.adopt_timer),
        ('create_service', NodeRuntime.adopt_service),
    )


def _wrap_factory(
    factory: Callable[..., Any],
    adopt: Callable[[NodeRuntime, Any], None],
    env: RuntimeEnv,
    *,
    bound_method: bool = False,
) -> Callable[..., Any]:
    """Wrap an entity factory (a class's method, or one node's bound method)."""

    def adopt_unless_internal(node: Node, entity: Any) -> Any:
        # rclpy creates its own entities through the same methods (the /parameter_events
        # publisher, the /clock subscription, Rate timers); those are not the node's inputs.
        caller = sys._getframe(2).f_globals.get('__name__', '')
        if not caller.startswith('rclpy.'):
            adopt(NodeRuntime.of(node, env), entity)
        return entity

    if bound_method:
        node: Node = factory.__self__  # type: ignore[attr-defined]

        @functools.wraps(factory)
        def create_bound(*args: Any, **kwargs: Any) -> Any:
            return adopt_unless_internal(node, factory(*args, **kwargs))

        return create_bound

    @functools.wraps(factory)
    def create(self: Node, *args: Any, **kwargs: Any) -> Any:
        return adopt_unless_internal(self, factory(self, *args, **kwargs))

    return create
