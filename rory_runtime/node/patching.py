"""How a node class gets its runtime: the decorator ``rory-instrument`` adds, and what it patches
(docs/architecture.md, "Taking over the node's entities").

Under the supervisor (``RORY_NODE`` set) :func:`checkpointed` wraps the class's ``__init__`` and
its entity factories (``create_subscription``, ``create_publisher``, ``create_timer``,
``create_service``): each entity the node makes is handed to its :class:`NodeRuntime`
(``adopt_*``), except those rclpy makes for itself. :func:`checkpoint_module` does the same for
the first Node a function-style module makes. Unsupervised, neither patches anything.
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from typing import Any, TypeVar

from rclpy.node import Node

from ..freshness import rules_from
from .runtime import NodeRuntime, RuntimeEnv
from .state import CheckpointSpec

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
