"""A lifecycle node's state (docs/architecture.md, "Lifecycle nodes").

Checkpoints keep the node's primary state; a recovered process is taken back to it through
its own transition callbacks (``on_configure``, ``on_activate``, ...), so what they make (a
publisher, a timer, a buffer) exists again. Transitions requested from outside come through
the node's ``~/change_state`` service, which the runtime treats as one of the node's services:
held until release, each request logged and replayed in order.
"""

from __future__ import annotations

from typing import Any

from rclpy.node import Node

# The transitions (trigger methods of rclpy's LifecycleNodeMixin) from a primary state to
# another, by label.
PATHS: dict[tuple[str, str], tuple[str, ...]] = {
    ('unconfigured', 'inactive'): ('configure',),
    ('unconfigured', 'active'): ('configure', 'activate'),
    ('inactive', 'active'): ('activate',),
    ('inactive', 'unconfigured'): ('cleanup',),
    ('active', 'inactive'): ('deactivate',),
    ('active', 'unconfigured'): ('deactivate', 'cleanup'),
    ('unconfigured', 'finalized'): ('shutdown',),
    ('inactive', 'finalized'): ('shutdown',),
    ('active', 'finalized'): ('shutdown',),
}


def state_of(node: Node) -> str:
    """The node's primary state, or '' when it is not a lifecycle node.

    rclpy keeps it in the mixin's state machine; its only public reader is the node's own
    ``~/get_state`` service.
    """
    machine: Any = getattr(node, '_state_machine', None)
    if machine is None:
        return ''
    return str(machine.current_state[1])


def change_state_service(node: Node) -> Any:
    """The node's ``~/change_state`` service, if it is a lifecycle node with one."""
    return getattr(node, '_service_change_state', None)


def restore(node: Node, wanted: str) -> str | None:
    """Take the node from its state to ``wanted`` through its transition callbacks.

    Returns:
        None when it got there, else why not.
    """
    current = state_of(node)
    if not wanted or not current or current == wanted:
        return None
    path = PATHS.get((current, wanted))
    if path is None:
        return f'lifecycle: no way from {current} to {wanted}'
    from rclpy.lifecycle import TransitionCallbackReturn  # only lifecycle nodes need it

    for transition in path:
        result = getattr(node, f'trigger_{transition}')()
        if result != TransitionCallbackReturn.SUCCESS:
            return (f'lifecycle: {transition} returned {getattr(result, "name", result)} on the '
                    f'way from {current} to {wanted}; the node is {state_of(node)}')
    return None
