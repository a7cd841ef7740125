"""A node's parameters as state and as input (docs/architecture.md, "Parameters").

Every checkpoint keeps all of the node's parameters; a recovered process sets those whose
value differs from what its own start gave them, through ``Node.set_parameters``, so the
node's parameter callbacks run as they did when the value was first set. A change from
outside (the ``~/set_parameters`` services, which call ``set_parameters_atomically``) is an
input: logged before it is applied, replayed in order with the messages and ticks. A change a
node's own callback makes is replayed with that callback and is not logged twice.

Parameters travel as a serialized ``rcl_interfaces/msg/ParameterEvent`` (its
``changed_parameters``): the type rclpy publishes them in, which keeps every value's type.
"""

from __future__ import annotations

from collections.abc import Iterable

from rcl_interfaces.msg import ParameterEvent
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.serialization import deserialize_message, serialize_message

RECORD_TYPE = 'rcl_interfaces/msg/ParameterEvent'

def pack(parameters: Iterable[Parameter]) -> bytes:
    """The CDR bytes of ``parameters``."""
    event = ParameterEvent(changed_parameters=[p.to_parameter_msg() for p in parameters])
    return bytes(serialize_message(event))


def unpack(data: bytes) -> list[Parameter]:
    """The parameters :func:`pack` packed.

    Raises:
        ValueError: ``data`` is not a serialized ParameterEvent.
    """
    try:
        event = deserialize_message(data, ParameterEvent)
    except RuntimeError as err:  # rclpy's RMWError
        raise ValueError(f'not a ParameterEvent: {err}') from None
    return [Parameter.from_parameter_msg(msg) for msg in event.changed_parameters]


def snapshot(node: Node) -> bytes:
    """Every parameter the node has, packed."""
    names = node.list_parameters([], 0).names
    return pack(node.get_parameters(names))


def restore(node: Node, data: bytes) -> tuple[list[str], list[str]]:
    """Set the packed parameters whose value differs from the node's, with its callbacks.

    Returns:
        The names set, and one line per parameter that could not be set, saying why.
    """
    restored: list[str] = []
    refused: list[str] = []
    for wanted in unpack(data):
        if wanted.type_ == Parameter.Type.NOT_SET:
            continue
        if node.has_parameter(wanted.name) and (
                node.get_parameter(wanted.name).to_parameter_msg() == wanted.to_parameter_msg()):
            continue
        try:
            result = node.set_parameters([wanted])[0]
        except ParameterException as err:
            refused.append(f'parameter {wanted.name}: not restored: {err}')
            continue
        if result.successful:
            restored.append(wanted.name)
        else:
            refused.append(f'parameter {wanted.name}: not restored: the node refused it '
                           f'({result.reason or "no reason given"})')
    return restored, refused
