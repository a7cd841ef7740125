"""ROS message classes by name, and messages built from plain mappings.

``rosidl_runtime_py`` is not among the PyPI wheels, so this is the small part of it RORY needs,
and the only place RORY turns a type name into code. Names read from a checkpoint or a config
are data: a name is validated, then the package is checked *on disk* to be a generated ROS
message package before anything is imported, so no other installed package can be made to run.
"""

from __future__ import annotations

import importlib
import importlib.util
import re
from collections.abc import Mapping
from functools import cache
from pathlib import Path
from typing import Any, Final

from .errors import RoryError

TYPE_NAME_RE: Final = re.compile(r'([a-z][a-z0-9_]*)/msg/([A-Z][A-Za-z0-9]*)')
"""A ROS 2 message type name, 'pkg/msg/Name' (groups: package, name); always used with
fullmatch. The one rule for it: a ROS message in a checkpoint (codec.py) and a safe-state type
in the supervisor config are checked against it too."""

_INT_RANGES: Final = {
    'int8': (-(2**7), 2**7 - 1),
    'uint8': (0, 2**8 - 1),
    'byte': (0, 2**8 - 1),
    'char': (0, 2**8 - 1),
    'int16': (-(2**15), 2**15 - 1),
    'uint16': (0, 2**16 - 1),
    'int32': (-(2**31), 2**31 - 1),
    'uint32': (0, 2**32 - 1),
    'int64': (-(2**63), 2**63 - 1),
    'uint64': (0, 2**64 - 1),
}


class MessageTypeError(RoryError):
    """A message type name that is malformed or names no installed message."""


def message_type_name(cls: object) -> str | None:
    """'pkg/msg/Name' of a generated rclpy message class, or None if it is not one.

    Generated classes live in modules like ``std_msgs.msg._int64`` and have a metaclass that
    carries ``_TYPE_SUPPORT``; services, actions and look-alikes are not messages.
    """
    if not isinstance(cls, type):
        return None
    if not hasattr(type(cls), '_TYPE_SUPPORT') or not hasattr(cls, 'get_fields_and_field_types'):
        return None
    parts = cls.__module__.split('.')
    if len(parts) != 3 or parts[1] != 'msg' or not parts[2].startswith('_'):
        return None
    name = f'{parts[0]}/msg/{cls.__name__}'
    return name if TYPE_NAME_RE.fullmatch(name) else None


def type_name_of(msg_class: type) -> str:
    """'pkg/msg/Name' of a generated message class.

    Raises:
        MessageTypeError: ``msg_class`` is not a generated message class.
    """
    name = message_type_name(msg_class)
    if name is None:
        raise MessageTypeError(f'{msg_class!r} is not a ROS message class')
    return name


def _is_message_package(package: str) -> bool:
    # Without importing: the package must exist and hold what rosidl generates for messages.
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return False
    for location in spec.submodule_search_locations:
        root = Path(location)
        if (root / 'msg' / '__init__.py').is_file() and any(
            root.glob(f'{package}_s__rosidl_typesupport_*')
        ):
            return True
    return False


@cache
def get_message_class(type_name: str) -> type:
    """The class for 'pkg/msg/Name'.

    Raises:
        MessageTypeError: The name is malformed or names no installed message.
    """
    match = TYPE_NAME_RE.fullmatch(type_name) if isinstance(type_name, str) else None
    if match is None:
        raise MessageTypeError(f'{type_name!r} is not a message type name like pkg/msg/Name')
    package, name = match.groups()
    try:
        if not _is_message_package(package):
            raise MessageTypeError(f'ROS message package {package!r} is not installed')
        module = importlib.import_module(f'{package}.msg')
    except (ImportError, ValueError):
        raise MessageTypeError(f'message package {package!r} is not installed') from None
    cls = getattr(module, name, None)
    if message_type_name(cls) != type_name:
        raise MessageTypeError(f'{type_name} is not a message of package {package!r}')
    assert isinstance(cls, type)
    return cls


def build_message(type_name: str, fields: Mapping[str, Any], *, where: str = '') -> Any:
    """A message of ``type_name`` with ``fields`` set (nested mappings for nested messages).

    Raises:
        MessageTypeError: Unknown type, unknown field, or a value of the wrong type or out of
            range; the message names the field path, prefixed with ``where``.
    """
    msg = get_message_class(type_name)()
    _set_fields(msg, fields, where or type_name)
    return msg


def _check_value(path: str, ros_type: str, value: Any) -> None:
    # rclpy checks field values only with ROS_PYTHON_CHECK_FIELDS=1; a bad safe-state message
    # must fail at start-up with its field named, not at S1 inside serialize_message.
    if ros_type == 'boolean':
        ok = isinstance(value, bool)
    elif ros_type in _INT_RANGES:
        low, high = _INT_RANGES[ros_type]
        ok = isinstance(value, int) and not isinstance(value, bool) and low <= value <= high
    elif ros_type in ('float', 'double'):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
    elif ros_type.startswith(('string', 'wstring')):
        ok = isinstance(value, str)
    else:
        ok = True  # sequences and arrays: rclpy converts and checks their elements itself
    if not ok:
        raise MessageTypeError(f'{path}: {value!r} is not a valid {ros_type}')


def _set_fields(msg: Any, fields: Mapping[str, Any], where: str) -> None:
    known: dict[str, str] = msg.get_fields_and_field_types()
    for key, value in fields.items():
        path = f'{where}.{key}'
        if key not in known:
            raise MessageTypeError(f'{path}: no such field; fields are {", ".join(known)}')
        current = getattr(msg, key)
        if isinstance(value, Mapping):
            if message_type_name(type(current)) is None:
                raise MessageTypeError(f'{path}: is not a message, cannot set it from a mapping')
            _set_fields(current, value, path)
            continue
        _check_value(path, known[key], value)
        try:
            setattr(msg, key, value)
        except (AssertionError, TypeError, ValueError) as err:
            raise MessageTypeError(f'{path}: cannot set {value!r} ({known[key]}): {err}') from None
