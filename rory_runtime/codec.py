"""Checkpoint value codec: msgpack with extension types, never pickle.

A checkpoint holds the values of a node's key variables. It is data, never code: decoding
builds values only from the closed set of types below and never calls anything named by the
bytes. Decoding imports nothing but a ROS 2 message package, and only for a type name that
matches ``<package>/msg/<Type>`` exactly, and rclpy itself for ``Time`` and ``Duration``.

Values round-trip exactly, type and value:

- natively in msgpack: ``None``, ``bool``, ``int`` (64 bit), ``float``, ``str``, ``bytes``,
  ``list``, ``dict`` (any supported hashable keys, insertion order kept);
- as msgpack extension types, whose payload is itself msgpack unless noted:

  ====  ===========================  ==========================================================
  code  Python type                  payload
  ====  ===========================  ==========================================================
  1     ``tuple``                    array of the items
  2     ``set``                      array of the members
  3     ``frozenset``                array of the members
  4     ``bytearray``                the raw bytes (not msgpack)
  5     ``int`` > 64 bit             two's complement, big endian, minimal length (not msgpack)
  6     numpy ndarray                ``[dtype.str, shape, C-order data bytes]``
  7     numpy scalar                 ``[dtype.str, data bytes]``
  8     ROS 2 message                ``[type name, CDR bytes]`` (``rclpy.serialization``)
  9     ``enum.Enum`` member         ``[module, qualname, member name]``; for a ``Flag``
                                     combination, which has no name, the int value instead
  10    dataclass instance           ``[module, qualname, {field name: value}]``, all of
                                     ``dataclasses.fields()``, ``init=False`` ones too
  11    ``rclpy.time.Time``          ``[nanoseconds, clock type as int]``
  12    ``rclpy.duration.Duration``  nanoseconds
  13    ``collections.deque``        ``[maxlen or nil, array of the items]``
  14    ``collections.OrderedDict``  map of the items, in order
  15    ``numpy.random.Generator``   ``[bit generator name, its state dict]``; the bit
                                     generator is one of numpy's own (PCG64, PCG64DXSM,
                                     MT19937, Philox, SFC64), so a particle filter's random
                                     stream continues exactly where it was
  16    ``random.Random``            its ``getstate()`` tuple
  ====  ===========================  ==========================================================

Enum and dataclass classes are named by module and qualname, so they may be nested in a
class but not defined inside a function (refused when encoding). Decoding finds the class in
``sys.modules`` by plain dictionary look-ups, **never importing** (a node's modules are
loaded by the time its checkpoint is restored), and checks it is an Enum class or a
dataclass. An Enum member comes back as the very same member object (``is``). A dataclass
comes back **without running any of its code**: ``object.__new__(cls)``, then
``object.__setattr__`` for each field, which works for frozen and slotted classes too;
neither ``__init__`` nor ``__post_init__`` runs, because a checkpoint is data and restoring
it must not depend on, or trigger, what the class's code does. So that this loses nothing,
encoding refuses a dataclass instance carrying attributes that are not fields (except
``functools.cached_property`` caches, which are recomputed), a field that is not set, a
field that is a descriptor, and a dataclass deriving from a built-in type such as ``dict``.
Decoding refuses a class whose fields are no longer those stored (the code changed).

Anything else is refused with a :class:`CodecError` naming where the value sits, its type
and, for what is not state at all, why, e.g.
``variable 'cfg'['gains'][1]: cannot checkpoint a value of type _thread.lock (a lock or
other thread synchronization object, not state)``. In such paths ``[i]`` is a list, tuple or
deque index, ``['k']`` a dict value, ``.keys()[i]`` the i-th key of a dict, ``{i}`` the i-th
member of a set in iteration order and ``.f`` the field ``f`` of a dataclass. Subclasses of
supported types (``defaultdict``, ``Counter``, a namedtuple, ``np.matrix``...) are refused
too, because they would come back as their base type.

Decoding hostile bytes raises :class:`CodecError` and nothing else; the message names the
variable and, inside dataclasses, the field (``variable 'ekf'.mode: cannot decode: ...``).
One quirk: msgpack itself decodes its reserved timestamp extension (-1) to
``msgpack.Timestamp`` before any hook sees it; the codec never writes that extension, and
checkpoint files carry a checksum.
"""

from __future__ import annotations

import collections
import dataclasses
import enum
import functools
import math
import random
import re
import struct
import sys
import threading
import types
import weakref
from collections.abc import Callable, Iterable, Mapping
from typing import Any, Final, Generic

import msgpack
import numpy as np

from rory_runtime import chunks
from rory_runtime.errors import CodecError
from rory_runtime.msgtypes import (
    TYPE_NAME_RE,
    MessageTypeError,
    get_message_class,
    message_type_name,
)

EXT_TUPLE: Final = 1
EXT_SET: Final = 2
EXT_FROZENSET: Final = 3
EXT_BYTEARRAY: Final = 4
EXT_BIGINT: Final = 5
EXT_NDARRAY: Final = 6
EXT_NPSCALAR: Final = 7
EXT_ROSMSG: Final = 8
EXT_ENUM: Final = 9
EXT_DATACLASS: Final = 10
EXT_TIME: Final = 11
EXT_DURATION: Final = 12
EXT_DEQUE: Final = 13
EXT_ORDEREDDICT: Final = 14
EXT_NPRANDOM: Final = 15
EXT_PYRANDOM: Final = 16

# numpy's own bit generators, by name: decoding instantiates only these.
_BIT_GENERATORS: Final[dict[str, Callable[[], np.random.BitGenerator]]] = {
    'PCG64': np.random.PCG64,
    'PCG64DXSM': np.random.PCG64DXSM,
    'MT19937': np.random.MT19937,
    'Philox': np.random.Philox,
    'SFC64': np.random.SFC64,
}

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
    """Bytes that do not decode; turned into CodecError naming the variable at the boundary.

    Args:
        reason: What is wrong.
        path: Where inside the variable, as far as known (``.field`` inside dataclasses).
    """

    def __init__(self, reason: str, path: str = '') -> None:
        super().__init__(reason)
        self.path = path


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


class Snapshot:
    """Checkpoint variables taken at one instant, not yet packed (see :func:`snapshot_vars`)."""

    __slots__ = ('_arrays', '_lowered')

    def __init__(self, lowered: dict[object, object], arrays: list[_DeferredArray]) -> None:
        self._lowered = lowered
        self._arrays = arrays


_Spare = tuple[np.ndarray[Any, np.dtype[Any]], chunks.Digests | None]
"""A buffer and the digests of its chunks (None: not tracked)."""
_Spares = dict[tuple[str, str, tuple[int, ...]], list[_Spare]]
"""Spare buffers by (variable path, dtype string, shape)."""


class ArrayPool:
    """Buffers for the array copies of the next snapshot: those of the last one packed.

    A snapshot copies each array into memory of its own. Fresh memory from the kernel is
    written for the first time by that copy, and the page faults cost more than the copy:
    16 MB took the node's executor 24-28 ms at the 2nd-4th checkpoint of a run (numpy asks for
    huge pages for large arrays, which the kernel zeroes and may compact for), 7 ms without
    huge pages, 2.5-3 ms once the allocator happened to hand back memory already used. Handing
    each large array's buffer of the last packed snapshot to the next one makes that the case
    from the second checkpoint on. The pool holds one snapshot's large arrays at most (what
    the last :meth:`refill` gave it), so arrays that change shape or go away are let go.
    Buffers are matched by the variable's path, dtype and shape.

    With ``chunk_bytes``, a buffer also carries the digests of its chunks (chunks.py), and the
    next snapshot of the same variable copies only the chunks that differ
    (:func:`chunks.copy_changed`): the chunks it finds equal keep their digest, so that only
    the changed ones are hashed and written.

    Thread use: :meth:`take` on the thread that takes snapshots, :meth:`refill` and
    :meth:`prime` on the one that packs them; those build a new dict and swap it in whole. A buffer
    is only ever given to a new snapshot after the snapshot that had it was packed.

    Args:
        chunk_bytes: The chunk size whose digests buffers carry; 0: none.
    """

    MIN_BYTES = 1 << 16
    """Arrays below this are copied into new memory: their faults cost next to nothing."""

    def __init__(self, chunk_bytes: int = 0) -> None:
        self.chunk_bytes = chunk_bytes
        self._spare: _Spares = {}

    def take(self, key: str, dtype: str, shape: tuple[int, ...]) -> _Spare | None:
        """A spare C-order buffer of that variable path, dtype and shape with its digests, or
        None."""
        # Only this thread pops; a refill builds new lists and swaps the dict whole.
        spares = self._spare.get((key, dtype, shape))
        return spares.pop() if spares else None

    def prime(self, values: Mapping[str, object]) -> None:
        """Fault in buffers for the large top-level arrays among ``values``, if the pool is
        empty: run on a thread other than the executor's before the first snapshot, so that
        the first one finds written memory too (numpy fills with the GIL released).

        ``values`` may be read while the node changes them: only dtypes and shapes are used.
        """
        if self._spare:
            return
        spare: _Spares = {}
        for name, value in list(values.items()):
            if (type(value) is np.ndarray and value.dtype.kind in _NUMERIC_KINDS
                    and value.nbytes >= self.MIN_BYTES):
                buffer = np.empty(value.shape, dtype=value.dtype)
                buffer.fill(0)
                # The key a snapshot looks for: the variable's path (_path_str of its root).
                key = (repr(name), value.dtype.str, value.shape)
                spare.setdefault(key, []).append((buffer, None))
        if not self._spare:
            self._spare = spare

    def refill(self, snapshot: Snapshot) -> None:
        """Keep a packed snapshot's large arrays for the next one; the snapshot is done with.

        Call only after the snapshot's bytes are no longer used: packed by
        :func:`pack_snapshot`, or the pieces of :func:`pack_pieces` written (or given up).
        """
        spare: _Spares = {}
        for array in snapshot._arrays:
            if array.data.nbytes >= self.MIN_BYTES:
                key = (array.key, array.dtype, array.data.shape)
                spare.setdefault(key, []).append((array.data, array.digests))
        self._spare = spare
        snapshot._arrays = []

    def __len__(self) -> int:
        return sum(len(spares) for spares in self._spare.values())


def snapshot_vars(values: Mapping[str, object], pool: ArrayPool | None = None) -> Snapshot:
    """The first half of :func:`encode_vars`: everything that must see the values unchanged.

    Lowering builds new containers holding only immutable values, except for numpy arrays,
    which are copied (one memcpy) and packed later. So a node can go on changing its state
    as soon as this returns, and the costly part - packing, several copies of every large
    array - runs in :func:`pack_snapshot` off the node's executor.
    ``pack_snapshot(snapshot_vars(v)) == encode_vars(v)``, byte for byte.

    Args:
        values: The variables by name.
        pool: Where large arrays are copied to: the buffers of an earlier, packed snapshot
            (see :class:`ArrayPool`); without one, every copy is a new allocation.

    Raises:
        CodecError: As :func:`encode_vars`.
    """
    _local.defer_arrays = True
    _local.pool = pool
    _local.deferred = []
    try:
        lowered: dict[object, object] = {}
        for name, value in values.items():
            if type(name) is not str:
                msg = f'variable name {name!r} is not a str but {_type_label(type(name))}'
                raise CodecError(msg)
            lowered[name] = _lower_root(value, repr(name))
        deferred: list[_DeferredArray] = _local.deferred
    finally:
        _local.defer_arrays = False
        _local.pool = None
        _local.deferred = None
    return Snapshot(lowered, deferred)


def pack_snapshot(snapshot: Snapshot) -> bytes:
    """The second half of :func:`encode_vars`: the msgpack bytes of a snapshot.

    Raises:
        CodecError: msgpack refused the structure (nesting beyond its limit).
    """
    return _pack_checked(snapshot._lowered, 'checkpoint variables')


def pack_pieces(snapshot: Snapshot) -> list[chunks.Piece]:
    """The bytes of :func:`pack_snapshot` as pieces, the large arrays not copied: packed bytes,
    and each large array's bytes in its snapshot buffer (:class:`chunks.Tracked`, with what
    is known of its chunks). Joined, they are ``pack_snapshot(snapshot)``, byte for byte.

    The buffers stay the snapshot's until :meth:`ArrayPool.refill` takes them back.

    Raises:
        CodecError: As :func:`pack_snapshot`, or an array too large for msgpack.
    """
    packer = msgpack.Packer(default=_pack_default, use_bin_type=True, strict_types=True,
                            unicode_errors=_UNICODE_ERRORS, autoreset=False)
    pieces: list[chunks.Piece] = []
    try:
        packer.pack_map_header(len(snapshot._lowered))
        for name, value in snapshot._lowered.items():
            packer.pack(name)
            _pack_walk(value, packer, pieces)
    except (ValueError, TypeError, OverflowError) as err:
        raise CodecError(f'checkpoint variables: cannot encode: {err}') from None
    pieces.append(packer.bytes())
    return pieces


def _pack_walk(value: object, packer: msgpack.Packer, pieces: list[chunks.Piece]) -> None:
    """Pack ``value`` into ``packer``, a large array as a piece of its own. Only containers
    lowering marked as holding deferred arrays are walked; the rest msgpack packs whole."""
    kind = type(value)
    if kind is _DeferredArray:
        assert isinstance(value, _DeferredArray)
        if value.data.nbytes < ArrayPool.MIN_BYTES:
            packer.pack(value)  # small: inline, through _pack_default
            return
        pieces.append(packer.bytes())
        packer.reset()
        pieces.append(_ndarray_head(value.dtype, value.shape, value.data.nbytes))
        data = value.data.data.cast('B')
        step = chunks.CHUNK_BYTES if value.digests is None else value.chunk_bytes
        if value.digests is None:
            value.digests = [None] * chunks.chunk_count(data.nbytes, step)
        pieces.append(chunks.Tracked(data, value.digests, step))
    elif kind is _ListWithArrays:
        assert isinstance(value, list)
        packer.pack_array_header(len(value))
        for item in value:
            _pack_walk(item, packer, pieces)
    elif kind is _DictWithArrays:
        assert isinstance(value, dict)
        packer.pack_map_header(len(value))
        for key, item in value.items():
            packer.pack(key)
            _pack_walk(item, packer, pieces)
    else:
        packer.pack(value)


def _ndarray_head(dtype: str, shape: list[int], nbytes: int) -> bytes:
    """The bytes :func:`_pack_default` writes for an array of ``nbytes`` >= 64 KiB
    (ArrayPool.MIN_BYTES) before its data: the extension header (ext 32, code EXT_NDARRAY)
    and its payload's start, ``[dtype, shape,`` and the data's bin 32 header."""
    payload = b'\x93' + _pack_payload(dtype) + _pack_payload(shape) + b'\xc6'
    length = len(payload) + 4 + nbytes
    if nbytes < 1 << 16 or length >= 1 << 32:
        msg = f'a numpy array of {nbytes} bytes does not fit msgpack\'s bin 32'
        raise ValueError(msg)
    return b'\xc9' + struct.pack('>Ib', length, EXT_NDARRAY) + payload + struct.pack('>I', nbytes)


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


class _DeferredArray:
    """An ndarray in a snapshot: a private C-order copy whose payload is packed later.

    A large one is keyed by its variable path, so that its buffer goes to the same variable's
    next snapshot, and with a chunking pool carries the digests of its chunks (ArrayPool).
    """

    __slots__ = ('chunk_bytes', 'data', 'digests', 'dtype', 'key', 'shape')

    def __init__(
        self, array: np.ndarray[Any, np.dtype[Any]], pool: ArrayPool | None, path: _Path
    ) -> None:
        self.dtype = array.dtype.str
        self.shape = list(array.shape)
        self.key = ''
        self.digests: chunks.Digests | None = None
        self.chunk_bytes = 0
        spare = None
        if pool is not None and array.nbytes >= ArrayPool.MIN_BYTES:
            self.key = _path_str(path)
            spare = pool.take(self.key, self.dtype, array.shape)
        buffer, known = spare if spare is not None else (None, None)
        if buffer is None:
            buffer = np.empty(array.shape, dtype=array.dtype)  # C order
        if pool is not None and pool.chunk_bytes and array.nbytes >= ArrayPool.MIN_BYTES:
            self.chunk_bytes = pool.chunk_bytes
            self.digests = chunks.copy_changed(buffer, array, known, pool.chunk_bytes)
        else:
            np.copyto(buffer, array, casting='no')
        self.data = buffer


class _ListWithArrays(list[object]):
    """A lowered list holding deferred arrays (in a snapshot): :func:`pack_pieces` walks it."""


class _DictWithArrays(dict[object, object]):
    """A lowered dict holding deferred arrays (in a snapshot): :func:`pack_pieces` walks it."""


def _pack_payload(obj: object) -> bytes:
    # Its own Packer: this runs inside the default hook, while the thread's main Packer is
    # in the middle of a pack().
    packer: msgpack.Packer | None = getattr(_local, 'payload_packer', None)
    if packer is None:
        packer = msgpack.Packer(use_bin_type=True, strict_types=True,
                                unicode_errors=_UNICODE_ERRORS)
        _local.payload_packer = packer
    packed: bytes = packer.pack(obj)
    return packed


def _pack_default(obj: object) -> object:
    """Called by msgpack for ints beyond 64 bit and for a snapshot's arrays; lowering has
    handled everything else."""
    if type(obj) is _DeferredArray:
        return _ext(EXT_NDARRAY, _pack_payload([obj.dtype, obj.shape, obj.data.tobytes()]))
    if type(obj) is _ListWithArrays:
        return list(obj)
    if type(obj) is _DictWithArrays:
        return dict(obj)
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
_AT_FIELD: Final = '.{}'


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
    if type(value) is collections.deque:
        return _ext(EXT_DEQUE, _pack([value.maxlen, _lower_items(value, path)]))
    if type(value) is collections.OrderedDict:
        return _ext(EXT_ORDEREDDICT, _pack(_lower_dict(value, path)))
    if type(value) is np.random.Generator:
        return _lower_nprandom(value, path)
    if type(value) is random.Random:
        return _ext(EXT_PYRANDOM, _pack(_lower(value.getstate(), path)))
    type_name = ros_type_name(kind)
    if type_name is not None:
        return _lower_rosmsg(value, type_name, path)
    if issubclass(kind, enum.Enum):
        assert isinstance(value, enum.Enum)
        return _lower_enum(value, kind, path)
    if dataclasses.is_dataclass(kind):
        return _lower_dataclass(value, kind, path)
    if kind is _loaded_class('rclpy.time', 'Time'):
        ns, clock = value.nanoseconds, int(value.clock_type)  # type: ignore[attr-defined]
        return _ext(EXT_TIME, _pack([ns, clock]))
    if kind is _loaded_class('rclpy.duration', 'Duration'):
        return _ext(EXT_DURATION, _pack(value.nanoseconds))  # type: ignore[attr-defined]
    hint = _not_state_hint(value, kind)
    label = _type_label(kind)
    raise _refuse(path, f'a value of type {label}' + (f' ({hint})' if hint else ''))


def _loaded_class(module: str, name: str) -> object:
    """module.name if that module is loaded, else None; a value's class implies its module."""
    loaded = sys.modules.get(module)
    return None if loaded is None else vars(loaded).get(name)


def _lower_items(items: Iterable[object], path: _Path) -> list[object]:
    out = list(items)
    deferred = _deferred_count()
    for index, item in enumerate(out):
        if type(item) not in _NATIVE:
            out[index] = _lower(item, (path, _AT_INDEX, index))
    if _deferred_count() > deferred:
        return _ListWithArrays(out)
    return out


def _deferred_count() -> int:
    """How many arrays the snapshot being taken has deferred so far (-1: none is)."""
    deferred: list[_DeferredArray] | None = getattr(_local, 'deferred', None)
    return -1 if deferred is None else len(deferred)


def _lower_members(members: set[object] | frozenset[object], path: _Path) -> list[object]:
    out = list(members)
    for index, item in enumerate(out):
        if type(item) not in _NATIVE:
            out[index] = _lower(item, (path, _AT_MEMBER, index))
    return out


def _lower_dict(mapping: dict[object, object], path: _Path) -> dict[object, object]:
    out: dict[object, object] = {}
    deferred = _deferred_count()
    for index, (key, item) in enumerate(mapping.items()):
        lowered_key = key if type(key) in _NATIVE else _lower(key, (path, _AT_KEY, index))
        if type(item) not in _NATIVE:
            item = _lower(item, (path, _AT_VALUE, key))
        out[lowered_key] = item
    if len(out) != len(mapping):
        # Distinct Python keys that encode alike would silently merge on decode.
        raise _refuse(path, 'a dict two of whose keys have the same encoding')
    if _deferred_count() > deferred:
        return _DictWithArrays(out)
    return out


def _lower_nprandom(generator: np.random.Generator, path: _Path) -> msgpack.ExtType:
    bit_generator = generator.bit_generator
    name = type(bit_generator).__name__
    if _BIT_GENERATORS.get(name) is not type(bit_generator):
        raise _refuse(path, f'a numpy Generator over the bit generator {name}')
    return _ext(EXT_NPRANDOM, _pack([name, _lower(bit_generator.state, path)]))


def _lower_ndarray(
    array: np.ndarray[Any, np.dtype[Any]], path: _Path
) -> msgpack.ExtType | _DeferredArray:
    dtype = array.dtype
    if dtype.kind not in _NUMERIC_KINDS:
        raise _refuse(path, f'a numpy array of dtype {dtype} (only bool and numeric dtypes)')
    if getattr(_local, 'defer_arrays', False):
        deferred = _DeferredArray(array, _local.pool, path)
        _local.deferred.append(deferred)
        return deferred
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


def _lower_enum(member: enum.Enum, kind: type[enum.Enum], path: _Path) -> msgpack.ExtType:
    reason = _unnamed_class_reason(kind)
    if reason is not None:
        raise _refuse(path, f'a value of type {_type_label(kind)} ({reason})')
    key: object = member._name_
    if key is None or kind._member_map_.get(member._name_) is not member:
        # A Flag combination (or an empty Flag) is no member of its own: stored by value.
        key = member._value_
        if not isinstance(member, enum.Flag) or type(key) is not int:
            msg = f'a value of type {_type_label(kind)} (an Enum member without a name)'
            raise _refuse(path, msg)
    return _ext(EXT_ENUM, _pack([kind.__module__, kind.__qualname__, key]))


def _lower_dataclass(value: object, kind: type, path: _Path) -> msgpack.ExtType:
    layout = _dataclass_layout(kind)
    reason = layout.refusal or _unnamed_class_reason(kind)
    if reason is None:
        # Attributes that are not fields would be lost: decoding runs no __post_init__.
        attributes = getattr(value, '__dict__', None)
        if attributes is not None and not layout.attributes.issuperset(attributes):
            lost = ', '.join(sorted(str(a) for a in attributes if a not in layout.attributes))
            reason = f'its attributes {lost} are not dataclass fields and would be lost'
    if reason is not None:
        raise _refuse(path, f'a value of type {_type_label(kind)} ({reason})')
    fields: dict[str, object] = {}
    for name in layout.fields:
        try:
            item = getattr(value, name)
        except AttributeError:
            raise _refuse((path, _AT_FIELD, name), 'a dataclass field that is not set') from None
        fields[name] = item if type(item) in _NATIVE else _lower(item, (path, _AT_FIELD, name))
    return _ext(EXT_DATACLASS, _pack([kind.__module__, kind.__qualname__, fields]))


def ros_type_name(cls: type) -> str | None:
    """Return the ROS 2 type name of a generated message class, or None if it is not one."""
    return message_type_name(cls)


def _type_label(kind: type) -> str:
    module = kind.__module__
    return kind.__qualname__ if module == 'builtins' else f'{module}.{kind.__qualname__}'


_ROS_ENTITY: Final = 'a ROS entity, not state'
_SYNC: Final = 'a lock or other thread synchronization object, not state'

# What a node holds that is not state, by (module, qualname) of a class in the value's MRO:
# no import needed, since a value of one of these classes means its module is loaded.
_NOT_STATE: Final[dict[tuple[str, str], str]] = {
    **dict.fromkeys(
        [
            ('rclpy.node', 'Node'),
            ('rclpy.publisher', 'Publisher'),
            ('rclpy.subscription', 'Subscription'),
            ('rclpy.timer', 'Timer'),
            ('rclpy.timer', 'Rate'),
            ('rclpy.client', 'Client'),
            ('rclpy.service', 'Service'),
            ('rclpy.waitable', 'Waitable'),  # action clients and servers among others
            ('rclpy.guard_condition', 'GuardCondition'),
            ('rclpy.clock', 'Clock'),
            ('rclpy.time_source', 'TimeSource'),
            ('rclpy.executors', 'Executor'),
            ('rclpy.callback_groups', 'CallbackGroup'),
            ('rclpy.context', 'Context'),
            ('rclpy.task', 'Future'),
            ('rclpy.impl.rcutils_logger', 'RcutilsLogger'),
        ],
        _ROS_ENTITY,
    ),
    **dict.fromkeys(
        [
            ('_thread', 'lock'),
            ('_thread', 'RLock'),
            ('threading', '_RLock'),
            ('threading', 'Condition'),
            ('threading', 'Semaphore'),
            ('threading', 'Event'),
            ('threading', 'Barrier'),
        ],
        _SYNC,
    ),
    ('threading', 'Thread'): 'a thread, not state',
    ('_io', '_IOBase'): 'an open file or stream, not state',
    ('_socket', 'socket'): 'a socket, not state',
    ('collections', 'defaultdict'): 'its default_factory is code; use a plain dict',
}

_CODE_TYPES: Final = (
    types.FunctionType,
    types.BuiltinFunctionType,
    types.MethodType,
    types.MethodWrapperType,
    types.WrapperDescriptorType,
    types.MethodDescriptorType,
    functools.partial,
)
_SUPPORTED_BASES: Final = (
    int, float, str, bytes, bytearray, list, tuple, dict, set, frozenset, np.ndarray,
)  # fmt: skip
_HEAPTYPE: Final = 1 << 9  # Py_TPFLAGS_HEAPTYPE: a class made by a class statement


def _not_state_hint(value: object, kind: type) -> str | None:
    """Why an unsupported value is not what a checkpoint can hold, in plain words."""
    if isinstance(value, type):
        return f'the class {_type_label(value)} itself: a class is code, not state'
    for base in kind.__mro__:
        hint = _NOT_STATE.get((base.__module__, base.__qualname__))
        if hint is not None:
            return hint
    if isinstance(value, types.ModuleType):
        return 'a module: code, not state'
    if isinstance(value, _CODE_TYPES):
        return 'a function or method: code, not state'
    if isinstance(value, types.GeneratorType | types.CoroutineType | types.AsyncGeneratorType):
        return 'a generator or coroutine, not state'
    if hasattr(kind, '__next__'):
        return 'an iterator, not state'
    if hasattr(type(kind), '_TYPE_SUPPORT'):
        return 'a ROS service or action type; only messages (pkg/msg/Type) are supported'
    for base in _SUPPORTED_BASES:
        if isinstance(value, base):
            plain = _type_label(base)
            return f'a subclass of {plain}, which would come back as a plain {plain}'
    if kind.__flags__ & _HEAPTYPE and hasattr(value, '__dict__'):
        return 'a plain object; make its class a dataclass to checkpoint it'
    return None


# --------------------------------------------------------------------------- classes by name


@functools.lru_cache(maxsize=4096)
def _dotted_parts(name: str) -> tuple[str, ...] | None:
    """The parts of a dotted name like ``Outer.Inner``, or None if it is not one."""
    parts = tuple(name.split('.'))
    return parts if all(part.isidentifier() for part in parts) else None


def _find_class(module: object, qualname: object, what: str) -> type:
    """The class ``module.qualname`` among the loaded modules; never imports anything.

    Plain look-ups in a module's or class's own ``__dict__``: no module ``__getattr__``,
    descriptor or metaclass hook runs.

    Raises:
        _Malformed: A name is malformed, the module is not loaded or holds no such class.

    """
    parts = _dotted_parts(qualname) if type(qualname) is str else None
    if parts is None or type(module) is not str or _dotted_parts(module) is None:
        msg = f'bad {what} class name {module!r}, {qualname!r}'
        raise _Malformed(msg)
    found: object = sys.modules.get(module)
    if not issubclass(type(found), types.ModuleType):
        msg = f'{what} class {module}.{qualname}: module {module!r} is not loaded'
        raise _Malformed(msg)
    for part in parts:
        found = vars(found).get(part)
        if not issubclass(type(found), type):
            msg = f'{what} class {module}.{qualname} does not exist in module {module!r}'
            raise _Malformed(msg)
    assert isinstance(found, type)
    return found


def _unnamed_class_reason(kind: type) -> str | None:
    """Why decoding could not find kind again by module and qualname; None if it can."""
    if '<locals>' in kind.__qualname__:
        return (
            'its class is defined inside a function; a checkpoint names a class by module'
            ' and qualname, so define it at module level or nested in a class'
        )
    try:
        found: type | None = _find_class(kind.__module__, kind.__qualname__, 'the')
    except _Malformed:
        found = None
    if found is not kind:
        return f'its class is not the one named {kind.__module__}.{kind.__qualname__}'
    return None


@dataclasses.dataclass(frozen=True, slots=True)
class _Layout:
    """What the codec needs to know about a dataclass, computed once per class."""

    fields: tuple[str, ...]
    """Names of all fields, in definition order."""
    field_set: frozenset[str]
    attributes: frozenset[str]
    """Instance attributes that may be present: the fields, and cached_property caches."""
    refusal: str | None
    """Why instances cannot round-trip, or None."""


_PLAIN_BASES: Final = frozenset({object, Generic})
_layouts: weakref.WeakKeyDictionary[type, _Layout] = weakref.WeakKeyDictionary()


def _dataclass_layout(cls: type) -> _Layout:
    layout = _layouts.get(cls)
    if layout is None:
        layout = _layouts[cls] = _make_layout(cls)
    return layout


def _make_layout(cls: type) -> _Layout:
    fields = tuple(field.name for field in dataclasses.fields(cls))
    attributes: dict[str, object] = {}
    for base in reversed(cls.__mro__):
        attributes.update(vars(base))
    cached = {k for k, v in attributes.items() if isinstance(v, functools.cached_property)}
    refusal: str | None = None
    for base in cls.__mro__:
        if base not in _PLAIN_BASES and not base.__flags__ & _HEAPTYPE:
            # object.__new__ cannot make it, and fields alone would not hold its contents.
            refusal = f'a dataclass deriving from {_type_label(base)}'
            break
    for name in fields:
        attribute = attributes.get(name)
        if refusal is None and _is_data_descriptor(attribute):
            refusal = f'its field {name!r} is a descriptor: setting it would run code'
    return _Layout(fields, frozenset(fields), frozenset(fields) | cached, refusal)


def _is_data_descriptor(attribute: object) -> bool:
    # Slots are descriptors too, but plain storage.
    kind = type(attribute)
    is_descriptor = hasattr(kind, '__set__') or hasattr(kind, '__delete__')
    return is_descriptor and kind is not types.MemberDescriptorType


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
    return CodecError(f'{subject}{_path_of(err)}: cannot decode: {_reason(err)}')


def _path_of(err: Exception) -> str:
    return err.path if isinstance(err, _Malformed) else ''


def _reason(err: Exception) -> str:
    if isinstance(err, _Malformed):
        return str(err)
    if isinstance(err, msgpack.OutOfData):
        return 'truncated data'
    if isinstance(err, msgpack.FormatError):
        return 'invalid msgpack format byte'
    if isinstance(err, msgpack.StackError | RecursionError):
        return 'nested too deeply'
    return f'{type(err).__name__}: {err}'


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
    # The name is checked before anything is imported for it.
    if type(type_name) is not str or not TYPE_NAME_RE.fullmatch(type_name):
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


def _decode_enum(data: bytes) -> object:
    module, qualname, key = _unpack_list(data, 'Enum member', 3)
    cls = _find_class(module, qualname, 'Enum')
    full = f'{module}.{qualname}'
    if not issubclass(cls, enum.Enum) or not cls._member_map_:
        msg = f'{full} is not an Enum class with members'
        raise _Malformed(msg)
    if type(key) is str:
        member = cls._member_map_.get(key)
        if member is None:
            msg = f'Enum {full} has no member {key!r}'
            raise _Malformed(msg)
        return member
    if type(key) is int and issubclass(cls, enum.Flag):
        return _flag_combination(cls, key, full)
    msg = f'malformed member of Enum {full}: {key!r}'
    raise _Malformed(msg)


# The enum module's own way to make a Flag combination, which Flag(value) calls unless the
# class overrides _missing_; used directly so that no code of the class runs.
_FLAG_MISSING: Final[Callable[[type[enum.Flag], int], object]] = vars(enum.Flag)[
    '_missing_'
].__func__


def _flag_combination(cls: type[enum.Flag], value: int, full: str) -> enum.Flag:
    member = cls._value2member_map_.get(value)
    if member is None:
        try:
            member = _FLAG_MISSING(cls, value)  # type: ignore[assignment]
        except ValueError:
            member = None
    # The encoder writes the value of an existing member, never one the boundary changes.
    if not isinstance(member, cls) or member._value_ != value:
        msg = f'Flag {full} has no value {value}'
        raise _Malformed(msg)
    return member


def _decode_dataclass(data: bytes) -> object:
    unpacker = _unpacker(data)
    if unpacker.read_array_header() != 3:
        msg = 'malformed dataclass payload'
        raise _Malformed(msg)
    module, qualname = unpacker.unpack(), unpacker.unpack()
    cls = _find_class(module, qualname, 'dataclass')
    full = f'{module}.{qualname}'
    if not dataclasses.is_dataclass(cls):
        msg = f'{full} is not a dataclass'
        raise _Malformed(msg)
    layout = _dataclass_layout(cls)
    if layout.refusal is not None:
        msg = f'dataclass {full} cannot be restored: {layout.refusal}'
        raise _Malformed(msg)
    values: dict[str, object] = {}
    for _ in range(unpacker.read_map_header()):
        name = unpacker.unpack()
        if type(name) is not str or not name.isidentifier() or name in values:
            msg = f'bad field name {name!r} for dataclass {full}'
            raise _Malformed(msg)
        try:
            values[name] = unpacker.unpack()
        except Exception as err:
            raise _Malformed(_reason(err), f'.{name}{_path_of(err)}') from None
    if unpacker.tell() != len(data):
        msg = f'malformed payload for dataclass {full}'
        raise _Malformed(msg)
    if values.keys() != layout.field_set:
        raise _Malformed(_changed_fields(full, layout, values))
    # No __init__ or __post_init__: a checkpoint is data, and restoring it runs no code of
    # the class; object.__setattr__ also fills frozen and slotted dataclasses.
    instance = object.__new__(cls)
    for name in layout.fields:
        object.__setattr__(instance, name, values[name])
    return instance


def _changed_fields(full: str, layout: _Layout, values: Mapping[str, object]) -> str:
    new = [name for name in layout.fields if name not in values]
    gone = [name for name in values if name not in layout.field_set]
    differences = []
    if new:
        differences.append(f'not in the checkpoint: {", ".join(new)}')
    if gone:
        differences.append(f'no longer in the class: {", ".join(gone)}')
    return f'dataclass {full} has changed since the checkpoint; fields {"; ".join(differences)}'


_NS_RANGE: Final = range(-(2**63), 2**63)


def _decode_time(data: bytes) -> object:
    ns, clock = _unpack_list(data, 'rclpy Time', 2)
    if type(ns) is not int or not 0 <= ns < 2**63 or type(clock) is not int:
        msg = 'malformed rclpy Time payload'
        raise _Malformed(msg)
    from rclpy.clock_type import ClockType  # lazily: importing rclpy costs
    from rclpy.time import Time

    try:
        clock_type = ClockType(clock)
    except ValueError:
        msg = f'unknown clock type {clock} of rclpy Time'
        raise _Malformed(msg) from None
    return Time(nanoseconds=ns, clock_type=clock_type)


def _decode_duration(data: bytes) -> object:
    ns = _unpack(data)
    if type(ns) is not int or ns not in _NS_RANGE:
        msg = 'malformed rclpy Duration payload'
        raise _Malformed(msg)
    from rclpy.duration import Duration  # lazily: importing rclpy costs

    return Duration(nanoseconds=ns)


def _decode_deque(data: bytes) -> object:
    maxlen, items = _unpack_list(data, 'deque', 2)
    if (
        type(items) is not list
        or (maxlen is not None and type(maxlen) is not int)
        or (type(maxlen) is int and not len(items) <= maxlen <= sys.maxsize)
    ):
        msg = 'malformed deque payload'
        raise _Malformed(msg)
    return collections.deque(items, maxlen)


def _decode_ordereddict(data: bytes) -> object:
    items = _unpack(data)
    if type(items) is not dict:
        msg = 'malformed OrderedDict payload'
        raise _Malformed(msg)
    return collections.OrderedDict(items)


def _decode_nprandom(data: bytes) -> object:
    name, state = _unpack_list(data, 'numpy Generator', 2)
    factory = _BIT_GENERATORS.get(name) if type(name) is str else None
    if factory is None or type(state) is not dict:
        msg = 'malformed numpy Generator payload'
        raise _Malformed(msg)
    bit_generator = factory()
    try:
        bit_generator.state = state
    except (TypeError, ValueError, KeyError, IndexError, AttributeError, OverflowError) as err:
        msg = f'malformed numpy Generator state: {type(err).__name__}: {err}'
        raise _Malformed(msg) from None
    return np.random.Generator(bit_generator)


def _decode_pyrandom(data: bytes) -> object:
    state = _unpack(data)
    generator = random.Random()
    try:
        generator.setstate(state)  # type: ignore[arg-type]  # checked by setstate itself
    except (TypeError, ValueError, IndexError, OverflowError) as err:
        msg = f'malformed random.Random state: {type(err).__name__}: {err}'
        raise _Malformed(msg) from None
    return generator


_EXT_DECODERS: Final[dict[int, Callable[[bytes], object]]] = {
    EXT_TUPLE: _decode_tuple,
    EXT_SET: _decode_set,
    EXT_FROZENSET: _decode_frozenset,
    EXT_BYTEARRAY: _decode_bytearray,
    EXT_BIGINT: _decode_bigint,
    EXT_NDARRAY: _decode_ndarray,
    EXT_NPSCALAR: _decode_npscalar,
    EXT_ROSMSG: _decode_rosmsg,
    EXT_ENUM: _decode_enum,
    EXT_DATACLASS: _decode_dataclass,
    EXT_TIME: _decode_time,
    EXT_DURATION: _decode_duration,
    EXT_DEQUE: _decode_deque,
    EXT_ORDEREDDICT: _decode_ordereddict,
    EXT_NPRANDOM: _decode_nprandom,
    EXT_PYRANDOM: _decode_pyrandom,
}
