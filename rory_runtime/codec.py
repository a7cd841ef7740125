"""Checkpoint value codec: msgpack with extension types, never pickle.

A checkpoint holds the values of a node's key variables. It is data, never code: decoding
builds values only from the closed set of types below and never calls anything named by the
bytes. The one import decoding may trigger is that of a ROS 2 message package, and only for
a type name that matches ``<package>/msg/<Type>`` exactly.

Values round-trip exactly, type and value:

- natively in msgpack: ``None``, ``bool``, ``int`` (64 bit), ``float``, ``str``, ``bytes``,
  ``list``, ``dict`` (any supported hashable keys, insertion order kept);
- as msgpack extension types, whose payload is itself msgpack unless noted:

  ====  ================  ==========================================================
  code  Python type       payload
  ====  ================  ==========================================================
  1     ``tuple``         array of the items
  2     ``set``           array of the members
  3     ``frozenset``     array of the members
  4     ``bytearray``     the raw bytes (not msgpack)
  5     ``int`` > 64 bit  two's complement, big endian, minimal length (not msgpack)
  6     numpy ndarray     ``[dtype.str, shape, C-order data bytes]``
  7     numpy scalar      ``[dtype.str, data bytes]``
  8     ROS 2 message     ``[type name, CDR bytes]`` (``rclpy.serialization``)
  ====  ================  ==========================================================

Anything else is refused with a :class:`CodecError` naming where the value sits, e.g.
``variable 'cfg'['gains'][1]: cannot checkpoint a value of type _thread.lock``. In such
paths ``[i]`` is a list or tuple index, ``['k']`` a dict value, ``.keys()[i]`` the i-th key
of a dict and ``{i}`` the i-th member of a set in iteration order. Subclasses of supported
types (``IntEnum``, ``OrderedDict``, ``defaultdict``, ``np.matrix``...) are refused too,
because they would come back as their base type.

Decoding hostile bytes raises :class:`CodecError` and nothing else. One quirk: msgpack
itself decodes its reserved timestamp extension (-1) to ``msgpack.Timestamp`` before any hook
sees it; the codec never writes that extension, and checkpoint files carry a checksum.
"""

from __future__ import annotations

import math
import re
import threading
from collections.abc import Callable, Mapping
from typing import Any, Final

import msgpack
import numpy as np

from rory_runtime.errors import CodecError
from rory_runtime.msgtypes import MessageTypeError, get_message_class, message_type_name

EXT_TUPLE: Final = 1
EXT_SET: Final = 2
EXT_FROZENSET: Final = 3
EXT_BYTEARRAY: Final = 4
EXT_BIGINT: Final = 5
EXT_NDARRAY: Final = 6
EXT_NPSCALAR: Final = 7
EXT_ROSMSG: Final = 8

ROS_TYPE_RE: Final = re.compile(r'[a-z][a-z0-9_]*/msg/[A-Z][A-Za-z0-9]*')
"""Accepted ROS 2 message type names; checked before anything is imported."""

_NUMERIC_KINDS: Final = frozenset('biufc')
_DTYPE_RE: Final = re.compile(r'[<>|][biufc][0-9]{1,2}')
_MAX_NDIM: Final = 64  # numpy's own limit

# Types msgpack packs itself without losing the type; everything else is lowered to an
# ExtType first. int is here because msgpack hands out-of-range ints to the default hook.
_NATIVE: Final[frozenset[type]] = frozenset({type(None), bool, int, float, str, bytes})

_local = threading.local()

# Lone surrogates are legal in Python str; 'surrogatepass' lets them round-trip.
_UNICODE_ERRORS: Final = 'surrogatepass'


class _Malformed(Exception):
    """Bytes that do not decode; turned into CodecError naming the variable at the boundary."""


# --------------------------------------------------------------------------- encoding


def encode(value: object, *, name: str = 'value') -> bytes:
    """Encode one value.

    Args:
        value: The value to encode.
        name: Variable name used in error messages.

    Returns:
        The msgpack bytes.

    Raises:
        CodecError: The value, or something inside it, cannot be checkpointed.

    """
    subject = f'variable {name!r}'
    return _pack_checked(_lower_root(value, repr(name)), subject)


def encode_vars(values: Mapping[str, object]) -> bytes:
    """Encode a map of variable name to value.

    Args:
        values: The variables, in the order they should be stored.

    Returns:
        The msgpack bytes of a map from name to value.

    Raises:
        CodecError: A name is not a str, or a value cannot be checkpointed; the message
            names the variable and the path inside it.

    """
    lowered: dict[object, object] = {}
    for name, value in values.items():
        if type(name) is not str:
            msg = f'variable name {name!r} is not a str but {_type_label(type(name))}'
            raise CodecError(msg)
        lowered[name] = _lower_root(value, repr(name))
    return _pack_checked(lowered, 'checkpoint variables')


def _lower_root(value: object, root: str) -> object:
    try:
        return _lower(value, (root,))
    except RecursionError:
        msg = f'variable {root}: nested too deeply or contains a reference cycle'
        raise CodecError(msg) from None
    except (ValueError, TypeError, OverflowError) as err:
        # Raised by msgpack packing a finished sub-tree, e.g. beyond its nesting limit.
        msg = f'variable {root}: cannot encode: {err}'
        raise CodecError(msg) from None


def _pack_checked(lowered: object, subject: str) -> bytes:
    try:
        return _pack(lowered)
    except (ValueError, TypeError, OverflowError) as err:
        # msgpack's own nesting limit (512 levels) is the only expected way to get here.
        raise CodecError(f'{subject}: cannot encode: {err}') from None


def _pack(obj: object) -> bytes:
    # One Packer per thread: building one per call costs more than packing a small tuple.
    # Lowering packs finished sub-trees one after the other, never while a pack is under
    # way, and a Packer resets itself when pack() raises, so reuse is safe.
    packer: msgpack.Packer | None = getattr(_local, 'packer', None)
    if packer is None:
        packer = msgpack.Packer(
            default=_pack_default,
            use_bin_type=True,
            strict_types=True,
            unicode_errors=_UNICODE_ERRORS,
        )
        _local.packer = packer
    packed: bytes = packer.pack(obj)
    return packed


def _ext(code: int, payload: bytes) -> msgpack.ExtType:
    # ExtType.__new__ re-validates code and payload in Python, which doubles the cost of a
    # small tuple; ours are known-good constants and bytes.
    ext: msgpack.ExtType = tuple.__new__(msgpack.ExtType, (code, payload))
    return ext


def _pack_default(obj: object) -> object:
    """Called by msgpack for ints beyond 64 bit; lowering has handled everything else."""
    if type(obj) is int:
        length = (obj.bit_length() + 8) // 8  # room for the sign bit
        return _ext(EXT_BIGINT, obj.to_bytes(length, 'big', signed=True))
    msg = f'internal error: unlowered value of type {_type_label(type(obj))}'
    raise TypeError(msg)


# Where a value sits: (root,) or (parent path, template, key). It is formatted only for an
# error message; formatting it for every element would cost more than lowering the element.
_Path = tuple[Any, ...]
_AT_INDEX: Final = '[{}]'
_AT_VALUE: Final = '[{!r}]'
_AT_KEY: Final = '.keys()[{}]'
_AT_MEMBER: Final = '{{{}}}'


def _path_str(path: _Path) -> str:
    parts: list[str] = []
    while len(path) == 3:
        path, template, key = path
        parts.append(template.format(key))
    parts.append(path[0])
    return ''.join(reversed(parts))


def _refuse(path: _Path, what: str) -> CodecError:
    return CodecError(f'variable {_path_str(path)}: cannot checkpoint {what}')


def _lower(value: object, path: _Path) -> object:
    """Turn value into something msgpack packs exactly, or raise CodecError naming path."""
    kind = type(value)
    if kind in _NATIVE:
        return value
    # Exact type checks, not isinstance: a subclass would come back as its base class.
    if type(value) is list:
        return _lower_items(value, path)
    if type(value) is dict:
        return _lower_dict(value, path)
    if type(value) is tuple:
        return _ext(EXT_TUPLE, _pack(_lower_items(value, path)))
    if type(value) is set:
        return _ext(EXT_SET, _pack(_lower_members(value, path)))
    if type(value) is frozenset:
        return _ext(EXT_FROZENSET, _pack(_lower_members(value, path)))
    if type(value) is bytearray:
        return _ext(EXT_BYTEARRAY, bytes(value))
    if type(value) is np.ndarray:
        return _lower_ndarray(value, path)
    if isinstance(value, np.generic):
        return _lower_npscalar(value, path)
    type_name = ros_type_name(kind)
    if type_name is not None:
        return _lower_rosmsg(value, type_name, path)
    raise _refuse(path, f'a value of type {_type_label(kind)}')


def _lower_items(items: list[object] | tuple[object, ...], path: _Path) -> list[object]:
    out = list(items)
    for index, item in enumerate(out):
        if type(item) not in _NATIVE:
            out[index] = _lower(item, (path, _AT_INDEX, index))
    return out


def _lower_members(members: set[object] | frozenset[object], path: _Path) -> list[object]:
    out = list(members)
    for index, item in enumerate(out):
        if type(item) not in _NATIVE:
            out[index] = _lower(item, (path, _AT_MEMBER, index))
    return out


def _lower_dict(mapping: dict[object, object], path: _Path) -> dict[object, object]:
    out: dict[object, object] = {}
    for index, (key, item) in enumerate(mapping.items()):
        lowered_key = key if type(key) in _NATIVE else _lower(key, (path, _AT_KEY, index))
        if type(item) not in _NATIVE:
            item = _lower(item, (path, _AT_VALUE, key))
        out[lowered_key] = item
    if len(out) != len(mapping):
        # Distinct Python keys that encode alike would silently merge on decode.
        raise _refuse(path, 'a dict two of whose keys have the same encoding')
    return out


def _lower_ndarray(array: np.ndarray[Any, np.dtype[Any]], path: _Path) -> msgpack.ExtType:
    dtype = array.dtype
    if dtype.kind not in _NUMERIC_KINDS:
        raise _refuse(path, f'a numpy array of dtype {dtype} (only bool and numeric dtypes)')
    # tobytes() gives C order for any layout, so non-contiguous input needs no special case.
    payload = _pack([dtype.str, list(array.shape), array.tobytes()])
    return _ext(EXT_NDARRAY, payload)


def _lower_npscalar(scalar: np.generic, path: _Path) -> msgpack.ExtType:
    dtype = scalar.dtype
    if dtype.kind not in _NUMERIC_KINDS:
        raise _refuse(path, f'a numpy scalar of type {_type_label(type(scalar))}')
    return _ext(EXT_NPSCALAR, _pack([dtype.str, scalar.tobytes()]))


def _lower_rosmsg(message: object, type_name: str, path: _Path) -> msgpack.ExtType:
    from rclpy.serialization import serialize_message  # lazily: importing rclpy costs

    try:
        cdr = serialize_message(message)
    except Exception as err:
        # rclpy reports invalid field values with assorted exception types.
        raise _refuse(path, f'ROS message {type_name}: {err}') from None
    return _ext(EXT_ROSMSG, _pack([type_name, cdr]))


def ros_type_name(cls: type) -> str | None:
    """Return the ROS 2 type name of a generated message class, or None if it is not one."""
    return message_type_name(cls)


def _type_label(kind: type) -> str:
    module = kind.__module__
    return kind.__qualname__ if module == 'builtins' else f'{module}.{kind.__qualname__}'


# --------------------------------------------------------------------------- decoding


def decode(data: bytes, *, name: str = 'value') -> object:
    """Decode one value written by :func:`encode`.

    Args:
        data: The bytes.
        name: Variable name used in error messages.

    Returns:
        The value.

    Raises:
        CodecError: The bytes are not a valid encoding.

    """
    subject = f'variable {name!r}'
    unpacker = _unpacker(data)
    value = _unpack_next(unpacker, subject)
    _expect_end(unpacker, len(data), subject)
    return value


def decode_vars(data: bytes) -> dict[str, object]:
    """Decode a map of variable name to value written by :func:`encode_vars`.

    Args:
        data: The bytes.

    Returns:
        The variables, in stored order.

    Raises:
        CodecError: The bytes are not a valid encoding; names the variable where known.

    """
    unpacker = _unpacker(data)
    try:
        count = unpacker.read_map_header()
    except Exception as err:
        raise _decode_error('checkpoint variables', err) from None
    values: dict[str, object] = {}
    for index in range(count):
        name = _unpack_next(unpacker, f'name of variable #{index}')
        if type(name) is not str:
            msg = f'name of variable #{index}: is a {_type_label(type(name))}, not a str'
            raise CodecError(msg)
        values[name] = _unpack_next(unpacker, f'variable {name!r}')
    _expect_end(unpacker, len(data), 'checkpoint variables')
    return values


def _unpacker(data: bytes) -> msgpack.Unpacker:
    # Limits derive from max_buffer_size, so a length field in hostile bytes can never make
    # msgpack allocate more than the input; 0 would mean 4 GiB, hence the max(..., 1).
    unpacker = msgpack.Unpacker(
        ext_hook=_ext_hook,
        raw=False,
        use_list=True,
        strict_map_key=False,
        unicode_errors=_UNICODE_ERRORS,
        max_buffer_size=max(len(data), 1),
    )
    unpacker.feed(data)
    return unpacker


def _unpack_next(unpacker: msgpack.Unpacker, subject: str) -> object:
    try:
        return unpacker.unpack()
    except Exception as err:
        # Decoding untrusted bytes: whatever fails below (msgpack, numpy, rclpy, hashing an
        # unhashable set member...) is the data's fault and is reported as such.
        raise _decode_error(subject, err) from None


def _expect_end(unpacker: msgpack.Unpacker, size: int, subject: str) -> None:
    if unpacker.tell() != size:
        msg = f'{subject}: cannot decode: {size - unpacker.tell()} trailing bytes'
        raise CodecError(msg)


def _decode_error(subject: str, err: Exception) -> CodecError:
    reason: str
    if isinstance(err, _Malformed):
        reason = str(err)
    elif isinstance(err, msgpack.OutOfData):
        reason = 'truncated data'
    elif isinstance(err, msgpack.FormatError):
        reason = 'invalid msgpack format byte'
    elif isinstance(err, msgpack.StackError | RecursionError):
        reason = 'nested too deeply'
    else:
        reason = f'{type(err).__name__}: {err}'
    return CodecError(f'{subject}: cannot decode: {reason}')


def _ext_hook(code: int, data: bytes) -> object:
    decoder = _EXT_DECODERS.get(code)
    if decoder is None:
        msg = f'unknown extension type {code}'
        raise _Malformed(msg)
    return decoder(data)


def _unpack(data: bytes) -> object:
    return msgpack.unpackb(
        data,
        ext_hook=_ext_hook,
        raw=False,
        use_list=True,
        strict_map_key=False,
        unicode_errors=_UNICODE_ERRORS,
    )


def _unpack_list(data: bytes, what: str, length: int | None = None) -> list[object]:
    items = _unpack(data)
    if type(items) is not list or (length is not None and len(items) != length):
        msg = f'malformed {what} payload'
        raise _Malformed(msg)
    return items


def _decode_tuple(data: bytes) -> object:
    return tuple(_unpack_list(data, 'tuple'))


def _decode_set(data: bytes) -> object:
    return set(_unpack_list(data, 'set'))


def _decode_frozenset(data: bytes) -> object:
    return frozenset(_unpack_list(data, 'frozenset'))


def _decode_bytearray(data: bytes) -> object:
    return bytearray(data)


def _decode_bigint(data: bytes) -> object:
    if not data:
        msg = 'empty big integer payload'
        raise _Malformed(msg)
    return int.from_bytes(data, 'big', signed=True)


def _decode_dtype(spec: object) -> np.dtype[Any]:
    if type(spec) is not str or not _DTYPE_RE.fullmatch(spec):
        msg = f'unsupported numpy dtype {spec!r}'
        raise _Malformed(msg)
    try:
        dtype = np.dtype(spec)
    except TypeError:
        msg = f'unsupported numpy dtype {spec!r}'
        raise _Malformed(msg) from None
    if dtype.kind not in _NUMERIC_KINDS:
        msg = f'unsupported numpy dtype {spec!r}'
        raise _Malformed(msg)
    return dtype


def _decode_shape(shape: object) -> tuple[int, ...]:
    if (
        type(shape) is not list
        or len(shape) > _MAX_NDIM
        or not all(type(dim) is int and dim >= 0 for dim in shape)
    ):
        msg = f'malformed numpy shape {shape!r}'
        raise _Malformed(msg)
    return tuple(shape)


def _decode_ndarray(data: bytes) -> object:
    spec, shape_spec, raw = _unpack_list(data, 'ndarray', 3)
    dtype = _decode_dtype(spec)
    shape = _decode_shape(shape_spec)
    if type(raw) is not bytes:
        msg = 'malformed ndarray payload'
        raise _Malformed(msg)
    expected = math.prod(shape) * dtype.itemsize
    if len(raw) != expected:
        msg = (
            f'numpy array of dtype {spec} and shape {shape} needs {expected} bytes,'
            f' got {len(raw)}'
        )
        raise _Malformed(msg)
    # copy(): frombuffer returns a read-only view of the payload, callers want their own array.
    return np.frombuffer(raw, dtype=dtype).reshape(shape).copy()


def _decode_npscalar(data: bytes) -> object:
    spec, raw = _unpack_list(data, 'numpy scalar', 2)
    dtype = _decode_dtype(spec)
    if type(raw) is not bytes or len(raw) != dtype.itemsize:
        msg = f'malformed numpy scalar of dtype {spec}'
        raise _Malformed(msg)
    return np.frombuffer(raw, dtype=dtype)[0]


def _decode_rosmsg(data: bytes) -> object:
    type_name, cdr = _unpack_list(data, 'ROS message', 2)
    if type(type_name) is not str or not ROS_TYPE_RE.fullmatch(type_name):
        msg = f'bad ROS message type name {type_name!r}'
        raise _Malformed(msg)
    if type(cdr) is not bytes:
        msg = f'malformed ROS message payload for {type_name}'
        raise _Malformed(msg)
    cls = _message_class(type_name)
    from rclpy.serialization import deserialize_message  # lazily: importing rclpy costs

    try:
        return deserialize_message(cdr, cls)
    except Exception as err:
        msg = f'cannot deserialize ROS message {type_name}: {err}'
        raise _Malformed(msg) from None


def _message_class(type_name: str) -> type:
    """The class of a validated type name; nothing but a ROS message package is imported."""
    try:
        return get_message_class(type_name)
    except MessageTypeError:
        msg = f'ROS message type {type_name} is not installed'
        raise _Malformed(msg) from None


_EXT_DECODERS: Final[dict[int, Callable[[bytes], object]]] = {
    EXT_TUPLE: _decode_tuple,
    EXT_SET: _decode_set,
    EXT_FROZENSET: _decode_frozenset,
    EXT_BYTEARRAY: _decode_bytearray,
    EXT_BIGINT: _decode_bigint,
    EXT_NDARRAY: _decode_ndarray,
    EXT_NPSCALAR: _decode_npscalar,
    EXT_ROSMSG: _decode_rosmsg,
}
