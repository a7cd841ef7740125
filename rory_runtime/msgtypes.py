"""ROS message classes by name, and messages built from plain mappings.

``rosidl_runtime_py`` is not among the PyPI wheels, so this is the small part of it RORY needs.
Type names are validated before anything is imported: a name read from a file or a config can
only ever import ``<package>.msg`` of an installed package.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Mapping
from typing import Any, Final

from .errors import RoryError

TYPE_NAME_RE: Final = re.compile(r'^([a-z][a-z0-9_]*)/msg/([A-Z][A-Za-z0-9]*)$')


class MessageTypeError(RoryError):
    """A message type name that is malformed or names no installed message."""


def is_message_class(obj: object) -> bool:
    """Whether ``obj`` is a generated rclpy message class."""
    return (
        isinstance(obj, type)
        and hasattr(obj, 'get_fields_and_field_types')
        and hasattr(obj, '_TYPE_SUPPORT')
    )


def get_message_class(type_name: str) -> type:
    """The class for 'pkg/msg/Name'.

    Raises:
        MessageTypeError: The name is malformed or the package/message is not installed.
    """
    match = TYPE_NAME_RE.match(type_name)
    if match is None:
        raise MessageTypeError(f'{type_name!r} is not a message type name like pkg/msg/Name')
    package, name = match.groups()
    try:
        module = importlib.import_module(f'{package}.msg')
    except ImportError:
        raise MessageTypeError(f'message package {package!r} is not installed') from None
    cls = getattr(module, name, None)
    if not is_message_class(cls):
        raise MessageTypeError(f'{type_name} is not a message of package {package!r}')
    assert isinstance(cls, type)
    return cls


def type_name_of(msg_class: type) -> str:
    """'pkg/msg/Name' of a generated message class."""
    parts = msg_class.__module__.split('.')
    return f'{parts[0]}/{parts[1]}/{msg_class.__name__}'


def build_message(type_name: str, fields: Mapping[str, Any], *, where: str = '') -> Any:
    """A message of ``type_name`` with ``fields`` set (nested mappings for nested messages).

    Raises:
        MessageTypeError: Unknown type, unknown field or a value of the wrong kind; the
            message names the field path, prefixed with ``where``.
    """
    msg = get_message_class(type_name)()
    _set_fields(msg, fields, where or type_name)
    return msg


def _set_fields(msg: Any, fields: Mapping[str, Any], where: str) -> None:
    known = msg.get_fields_and_field_types()
    for key, value in fields.items():
        path = f'{where}.{key}'
        if key not in known:
            raise MessageTypeError(f'{path}: no such field; fields are {", ".join(known)}')
        current = getattr(msg, key)
        if isinstance(value, Mapping):
            if not is_message_class(type(current)):
                raise MessageTypeError(f'{path}: is not a message, cannot set it from a mapping')
            _set_fields(current, value, path)
            continue
        try:
            setattr(msg, key, value)
        except (AssertionError, TypeError, ValueError) as err:
            raise MessageTypeError(f'{path}: cannot set {value!r} ({known[key]}): {err}') from None
