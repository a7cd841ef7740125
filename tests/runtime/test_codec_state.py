"""Tests of the codec's state types: Enums, dataclasses, rclpy Time and Duration, deque and
OrderedDict, and its refusals of what is not state.

The Enum and dataclass classes live at module level here: this module is in sys.modules
whenever its values are decoded, as a node's own modules are when its checkpoint is restored.
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import enum
import functools
import io
import math
import socket
import sys
import threading
import time
import types
from collections import OrderedDict, deque
from typing import Any, Generic, TypeVar

import msgpack
import numpy as np
import pytest
import rclpy.client
import rclpy.node
import rclpy.publisher
import rclpy.service
import rclpy.subscription
import rclpy.timer
from geometry_msgs.msg import Point, Pose
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_budget import examples
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.clock_type import ClockType
from rclpy.duration import Duration
from rclpy.impl.rcutils_logger import RcutilsLogger
from rclpy.task import Future
from rclpy.time import Time
from std_msgs.msg import Int64

from rory_runtime.codec import (
    EXT_DATACLASS,
    EXT_DEQUE,
    EXT_DURATION,
    EXT_ENUM,
    EXT_ORDEREDDICT,
    EXT_TIME,
    decode,
    decode_vars,
    encode,
    encode_vars,
)
from rory_runtime.errors import CodecError

HERE = __name__  # the module name decoding looks the test classes up by

# --------------------------------------------------------------------------- test types


class Mode(enum.Enum):
    IDLE = 'idle'
    RUN = 'run'
    STOPPED = 'idle'  # an alias of IDLE


class Level(enum.IntEnum):
    LOW = 1
    HIGH = 2


class Colour(enum.StrEnum):
    RED = enum.auto()
    GREEN = enum.auto()


class Perm(enum.Flag):
    R = enum.auto()
    W = enum.auto()
    X = enum.auto()
    RW = R | W  # a named multi-bit member


class Bits(enum.IntFlag):  # boundary KEEP: unknown bits are kept
    A = 1
    B = 2
    C = 8


class Fresh(enum.Flag):
    """Only ever combined by decoding, to exercise building a combination."""

    A = 1
    B = 2
    C = 4


missing_calls: list[object] = []


class Picky(enum.Flag):
    A = 1
    B = 2

    @classmethod
    def _missing_(cls, value: object) -> Any:
        missing_calls.append(value)
        return super()._missing_(value)


class Holder:
    class Phase(enum.Enum):
        ONE = 1
        TWO = 2

    @dataclasses.dataclass
    class Cell:
        value: object
        phase: Holder.Phase = dataclasses.field(default_factory=lambda: Holder.Phase.ONE)


@dataclasses.dataclass
class Plain:
    x: object
    y: object = 0.0


@dataclasses.dataclass(frozen=True)
class Frozen:
    name: object
    gains: object = ()


@dataclasses.dataclass(slots=True)
class Slotted:
    a: object
    b: object = None


@dataclasses.dataclass(frozen=True, slots=True)
class FrozenSlotted:
    key: object
    value: object = None


@dataclasses.dataclass
class Child(Plain):
    z: object = 'child'


T = TypeVar('T')


@dataclasses.dataclass
class Box(Generic[T]):
    item: T


code_calls: list[str] = []


@dataclasses.dataclass
class Instrumented:
    """Records every run of its code; decoding must run none of it."""

    x: int
    doubled: int = dataclasses.field(init=False)
    _cls_note: dataclasses.InitVar[str] = 'note'

    def __new__(cls, *args: object, **kwargs: object) -> Instrumented:
        code_calls.append('__new__')
        return super().__new__(cls)

    def __post_init__(self, _cls_note: str) -> None:
        code_calls.append('__post_init__')
        self.doubled = self.x * 2

    def __setattr__(self, name: str, value: object) -> None:
        code_calls.append('__setattr__')
        super().__setattr__(name, value)


@dataclasses.dataclass
class Ekf:
    P: object
    x: object
    mode: Mode = Mode.IDLE
    history: object = dataclasses.field(default_factory=lambda: deque(maxlen=3))
    cells: list[Holder.Cell] = dataclasses.field(default_factory=list)
    pose: Pose = dataclasses.field(default_factory=Pose)
    stamp: Time = dataclasses.field(default_factory=Time)


@dataclasses.dataclass
class Cached:
    x: int

    @functools.cached_property
    def squared(self) -> int:
        return self.x * self.x


@dataclasses.dataclass
class WithLock:
    x: int

    def __post_init__(self) -> None:
        self._lock = threading.Lock()


@dataclasses.dataclass
class Unset:
    x: int
    later: int = dataclasses.field(init=False)


class Positive:
    """A descriptor used as a dataclass field type."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = '_' + name

    def __get__(self, obj: object, owner: type | None = None) -> int:
        return 1 if obj is None else int(getattr(obj, self.name))

    def __set__(self, obj: object, value: int) -> None:
        if value <= 0:
            raise ValueError('not positive')
        setattr(obj, self.name, value)


@dataclasses.dataclass
class WithDescriptor:
    n: Positive = Positive()


@dataclasses.dataclass
class Bag(dict[str, int]):
    label: str = ''


@dataclasses.dataclass
class Changed:
    a: int = 0
    b: int = 0


class Custom:
    pass


PointTuple = collections.namedtuple('PointTuple', 'x')


def function() -> None:
    pass


# --------------------------------------------------------------------------- helpers


def same(a: object, b: object) -> bool:
    """Equal in value *and* type, all the way down; nan equals nan, -0.0 differs from 0.0."""
    if type(a) is not type(b):
        return False
    if isinstance(a, enum.Enum):
        return a is b
    if isinstance(a, float):
        assert isinstance(b, float)
        if math.isnan(a):
            return math.isnan(b)
        return a == b and math.copysign(1, a) == math.copysign(1, b)
    if isinstance(a, list | tuple):
        assert isinstance(b, list | tuple)
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, deque):
        assert isinstance(b, deque)
        return a.maxlen == b.maxlen and same(list(a), list(b))
    if isinstance(a, dict):
        assert isinstance(b, dict)
        return len(a) == len(b) and all(
            same(ka, kb) and same(va, vb)
            for (ka, va), (kb, vb) in zip(a.items(), b.items(), strict=True)
        )
    if isinstance(a, set | frozenset):
        assert isinstance(b, set | frozenset)
        return len(a) == len(b) and all(any(same(x, y) for y in b) for x in a)
    if isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray)
        return a.dtype.str == b.dtype.str and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, np.generic):
        assert isinstance(b, np.generic)
        return a.dtype.str == b.dtype.str and a.tobytes() == b.tobytes()
    if dataclasses.is_dataclass(a):
        return all(
            same(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, Time):
        assert isinstance(b, Time)
        return a.nanoseconds == b.nanoseconds and a.clock_type == b.clock_type
    if isinstance(a, Duration):
        assert isinstance(b, Duration)
        return a.nanoseconds == b.nanoseconds
    return a == b  # ROS messages compare field by field


def roundtrip(value: object) -> object:
    return decode(encode(value))


def ext(code: int, payload: object) -> bytes:
    """Encoding of an extension value with a hand-made payload."""
    raw = payload if isinstance(payload, bytes) else msgpack.packb(payload, use_bin_type=True)
    return bytes(msgpack.packb(msgpack.ExtType(code, raw)))


def refusal(value: object, name: str = 'value') -> str:
    with pytest.raises(CodecError) as info:
        encode(value, name=name)
    return str(info.value)


def decode_refusal(data: bytes) -> str:
    with pytest.raises(CodecError) as info:
        decode(data)
    return str(info.value)


def make(cls: type, **fields: object) -> Any:
    """An instance of a dataclass built without running its code."""
    instance: Any = object.__new__(cls)
    for name, value in fields.items():
        object.__setattr__(instance, name, value)
    return instance


# --------------------------------------------------------------------------- Enums

MEMBERS: list[enum.Enum] = [
    Mode.IDLE,
    Mode.RUN,
    Mode.STOPPED,
    Level.LOW,
    Level.HIGH,
    Colour.RED,
    Perm.R,
    Perm.RW,
    Perm.R | Perm.X,
    Perm.R | Perm.W | Perm.X,
    Perm(0),
    Bits.A,
    Bits.A | Bits.C,
    Bits(0),
    Bits(1 | 4),  # a bit no member has, kept by IntFlag
    Holder.Phase.TWO,
    ClockType.ROS_TIME,  # an IntEnum of a library
]


@pytest.mark.parametrize('member', MEMBERS, ids=repr)
def test_enum_member_comes_back_as_the_same_object(member: enum.Enum) -> None:
    decoded = roundtrip(member)
    assert decoded is member


def test_int_and_str_enums_stay_enums() -> None:
    decoded = roundtrip([Level.HIGH, Colour.GREEN, 2, 'green'])
    assert isinstance(decoded, list)
    assert [type(v) for v in decoded] == [Level, Colour, int, str]


def test_enum_members_as_keys_and_set_members() -> None:
    value = {Mode.RUN: {Level.LOW, Perm.R | Perm.W}, (Mode.IDLE, 1): frozenset({Colour.RED})}
    assert same(roundtrip(value), value)


def test_flag_combination_is_built_without_the_class_code() -> None:
    # Nothing has made Fresh.A | Fresh.C yet: decoding builds it, and Flag's | finds it.
    decoded = decode(ext(EXT_ENUM, [HERE, 'Fresh', 5]))
    assert decoded is Fresh.A | Fresh.C
    # A class that overrides _missing_ does not get it called.
    decoded = decode(ext(EXT_ENUM, [HERE, 'Picky', 3]))
    assert not missing_calls
    assert decoded is Picky.A | Picky.B


@pytest.mark.parametrize(
    ('payload', 'reason'),
    [
        ([HERE, 'Mode', 'GONE'], f"Enum {HERE}.Mode has no member 'GONE'"),
        ([HERE, 'Mode', '_value2member_map_'], 'has no member'),
        ([HERE, 'Mode', 1], f'malformed member of Enum {HERE}.Mode: 1'),
        ([HERE, 'Perm', 64], f'Flag {HERE}.Perm has no value 64'),
        ([HERE, 'Perm', -1], f'Flag {HERE}.Perm has no value -1'),
        ([HERE, 'Perm', True], 'malformed member'),
        ([HERE, 'Perm', None], 'malformed member'),
        ([HERE, 'Gone', 'A'], f'Enum class {HERE}.Gone does not exist in module {HERE!r}'),
        ([HERE, 'Holder.Gone', 'A'], f'Enum class {HERE}.Holder.Gone does not exist'),
        ([HERE, 'Plain', 'x'], f'{HERE}.Plain is not an Enum class with members'),
        ([HERE, 'function', 'x'], 'does not exist'),  # a function, not a class
        ([HERE, 'MEMBERS', 'x'], 'does not exist'),  # a list, not a class
        ([HERE, 'Mode.IDLE', 'x'], 'does not exist'),  # a member, not a class
        (['collections', 'OrderedDict', 'x'], 'collections.OrderedDict is not an Enum class'),
        (['enum', 'Flag', 5], 'enum.Flag is not an Enum class with members'),
        (['no_such_module_rory', 'Mode', 'A'], "module 'no_such_module_rory' is not loaded"),
        (['os;rm', 'Mode', 'A'], 'bad Enum class name'),
        (['', 'Mode', 'A'], 'bad Enum class name'),
        ([HERE, 'Holder..Phase', 'ONE'], 'bad Enum class name'),
        ([HERE, '<locals>.Mode', 'A'], 'bad Enum class name'),
        ([1, 'Mode', 'A'], 'bad Enum class name'),
        ([HERE, 'Mode'], 'malformed Enum member payload'),
        ('text', 'malformed Enum member payload'),
    ],
)
def test_bad_enum_is_refused(payload: object, reason: str) -> None:
    message = decode_refusal(ext(EXT_ENUM, payload))
    assert message.startswith("variable 'value': cannot decode: ")
    assert reason in message


def test_enum_of_a_module_not_loaded_names_module_and_qualname_and_imports_nothing() -> None:
    module = 'tabnanny'  # in the standard library, loaded by nobody
    assert module not in sys.modules
    before = set(sys.modules)
    message = decode_refusal(ext(EXT_ENUM, [module, 'Outer.Kind', 'A']))
    assert message == (
        "variable 'value': cannot decode: Enum class tabnanny.Outer.Kind:"
        " module 'tabnanny' is not loaded"
    )
    assert set(sys.modules) == before


def test_class_lookup_runs_no_module_getattr(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[str] = []
    lazy = types.ModuleType('rory_test_lazy_module')

    def module_getattr(name: str) -> object:
        calls.append(name)
        return Mode

    lazy.__getattr__ = module_getattr  # type: ignore[method-assign]
    monkeypatch.setitem(sys.modules, 'rory_test_lazy_module', lazy)
    assert 'does not exist' in decode_refusal(ext(EXT_ENUM, ['rory_test_lazy_module', 'M', 'A']))
    assert not calls


def test_local_enum_is_refused_when_encoding() -> None:
    class Local(enum.Enum):
        A = 1

    message = refusal({'m': Local.A}, name='state')
    assert message.startswith("variable 'state'['m']: cannot checkpoint a value of type ")
    assert 'test_local_enum_is_refused_when_encoding.<locals>.Local' in message
    assert 'defined inside a function' in message


def test_enum_whose_class_was_replaced_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    old = Level.LOW
    monkeypatch.setattr(sys.modules[HERE], 'Level', enum.IntEnum('Level', 'LOW HIGH'))
    assert f'its class is not the one named {HERE}.Level' in refusal(old)


# --------------------------------------------------------------------------- dataclasses

DATACLASSES: list[object] = [
    Plain(1),
    Plain(x=[1, (2, 3)], y={'k': b'v'}),
    Frozen('arm', (1.0, 2.0)),
    Slotted(np.arange(3), Mode.RUN),
    FrozenSlotted(('a', 1), Frozen('x')),
    Child(1, 2.0, 'three'),
    Box([Box(1)]),
    Holder.Cell(3.5, Holder.Phase.TWO),
    Ekf(
        P=np.eye(3),
        x=np.zeros(3, dtype=np.float32),
        mode=Mode.RUN,
        history=deque([(1, 2.0), (2, 4.0)], maxlen=3),
        cells=[Holder.Cell(1), Holder.Cell(Plain(Perm.R | Perm.W))],
        pose=Pose(position=Point(x=1.0)),
        stamp=Time(nanoseconds=123, clock_type=ClockType.ROS_TIME),
    ),
]


@pytest.mark.parametrize('value', DATACLASSES, ids=lambda v: type(v).__qualname__)
def test_dataclass_roundtrip(value: object) -> None:
    decoded = roundtrip(value)
    assert type(decoded) is type(value)
    assert same(decoded, value)
    assert decoded is not value


def test_frozen_and_slotted_dataclasses_keep_their_nature() -> None:
    frozen = roundtrip(FrozenSlotted(1, 2))
    assert isinstance(frozen, FrozenSlotted)
    with pytest.raises(dataclasses.FrozenInstanceError):
        frozen.key = 3  # type: ignore[misc]
    assert not hasattr(frozen, '__dict__')
    assert hash(frozen) == hash(FrozenSlotted(1, 2))
    assert frozen == FrozenSlotted(1, 2)


def test_frozen_dataclasses_as_keys_and_members() -> None:
    value = {Frozen('a'): {FrozenSlotted(1)}, FrozenSlotted((1, 2)): frozenset({Frozen('b')})}
    assert same(roundtrip(value), value)


def test_decoding_a_dataclass_runs_none_of_its_code() -> None:
    value = Instrumented(4)
    assert value.doubled == 8
    data = encode(value)
    code_calls.clear()
    decoded = decode(data)
    assert not code_calls
    assert isinstance(decoded, Instrumented)
    assert (decoded.x, decoded.doubled) == (4, 8)


def test_cached_property_cache_is_not_state() -> None:
    value = Cached(3)
    assert value.squared == 9  # caches 'squared' in the instance
    decoded = roundtrip(value)
    assert isinstance(decoded, Cached)
    assert 'squared' not in vars(decoded)
    assert decoded.squared == 9


def test_dataclass_field_paths_in_refusals() -> None:
    with pytest.raises(CodecError) as info:
        encode_vars({'ekf': Ekf(P=threading.Lock(), x=0)})
    assert str(info.value) == (
        "variable 'ekf'.P: cannot checkpoint a value of type _thread.lock"
        ' (a lock or other thread synchronization object, not state)'
    )
    nested = Ekf(P=0, x=0, cells=[Holder.Cell(1), Holder.Cell({'f': function})])
    message = refusal({'filters': [nested]}, name='state')
    assert message.startswith("variable 'state'['filters'][0].cells[1].value['f']: ")


@pytest.mark.parametrize(
    ('value', 'path', 'reason'),
    [
        (WithLock(1), "'v'", 'its attributes _lock are not dataclass fields and would be lost'),
        (Unset(1), "'v'.later", 'a dataclass field that is not set'),
        (WithDescriptor(), "'v'", "its field 'n' is a descriptor: setting it would run code"),
        (Bag(label='x'), "'v'", 'a dataclass deriving from dict'),
    ],
    ids=['extra-attribute', 'unset-field', 'descriptor-field', 'builtin-base'],
)
def test_dataclasses_that_would_not_round_trip_are_refused(
    value: object, path: str, reason: str
) -> None:
    message = refusal(value, name='v')
    assert message.startswith(f'variable {path}: cannot checkpoint ')
    assert reason in message


def test_local_dataclass_is_refused_when_encoding() -> None:
    @dataclasses.dataclass
    class Local:
        x: int

    message = refusal(Local(1), name='cfg')
    assert message.startswith("variable 'cfg': cannot checkpoint a value of type ")
    assert 'defined inside a function' in message


def dataclass_bytes(qualname: str, fields: dict[Any, object], module: str = HERE) -> bytes:
    raw = msgpack.packb([module, qualname, fields], use_bin_type=True)
    return bytes(msgpack.packb(msgpack.ExtType(EXT_DATACLASS, raw)))


def test_changed_dataclass_is_refused_naming_class_and_fields() -> None:
    data = dataclass_bytes('Changed', {'a': 1, 'c': 3})
    message = decode_refusal(data)
    assert message == (
        f"variable 'value': cannot decode: dataclass {HERE}.Changed has changed since the"
        ' checkpoint; fields not in the checkpoint: b; no longer in the class: c'
    )
    assert decode(dataclass_bytes('Changed', {'b': 2, 'a': 1})) == Changed(1, 2)


def test_decode_errors_name_the_field() -> None:
    inner = msgpack.ExtType(EXT_ENUM, msgpack.packb(['no_such_module_rory', 'Mode', 'RUN']))
    cell = msgpack.ExtType(
        EXT_DATACLASS, msgpack.packb([HERE, 'Holder.Cell', {'value': [inner], 'phase': None}])
    )
    data = msgpack.packb(
        {'ekf': msgpack.ExtType(EXT_DATACLASS, msgpack.packb([HERE, 'Plain', {'x': cell}]))}
    )
    with pytest.raises(CodecError) as info:
        decode_vars(data)
    assert str(info.value) == (
        "variable 'ekf'.x.value: cannot decode: Enum class no_such_module_rory.Mode:"
        " module 'no_such_module_rory' is not loaded"
    )


@pytest.mark.parametrize(
    ('data', 'reason'),
    [
        (dataclass_bytes('Gone', {}), f'dataclass class {HERE}.Gone does not exist'),
        (dataclass_bytes('Mode', {}), f'{HERE}.Mode is not a dataclass'),
        (dataclass_bytes('Custom', {}), f'{HERE}.Custom is not a dataclass'),
        (dataclass_bytes('Plain', {}, module='tabnanny'), "module 'tabnanny' is not loaded"),
        (dataclass_bytes('Bag', {'label': ''}), 'cannot be restored: a dataclass deriving'),
        (dataclass_bytes('WithDescriptor', {'n': 1}), 'cannot be restored: its field'),
        (dataclass_bytes('Plain', {'x': 1, 'y': 2, 'z': 3}), 'no longer in the class: z'),
        (dataclass_bytes('Plain', {'x': 1, 1: 2}), 'bad field name 1'),
        (dataclass_bytes('Plain', {'x': 1, 'a b': 2}), "bad field name 'a b'"),
        (ext(EXT_DATACLASS, [HERE, 'Plain']), 'malformed dataclass payload'),
        (ext(EXT_DATACLASS, {'a': 1}), 'ValueError'),
        (ext(EXT_DATACLASS, [HERE, 'Plain', [1, 2]]), 'ValueError'),
        (ext(EXT_DATACLASS, msgpack.packb([HERE, 'Plain', {'x': 1, 'y': 2}]) + b'\x00'),
         'malformed payload for dataclass'),
        (ext(EXT_DATACLASS, msgpack.packb([HERE, 'Plain', {'x': 1, 'y': 2}])[:-1]),
         "variable 'value'.y: cannot decode: truncated data"),
    ],
)  # fmt: skip
def test_bad_dataclass_is_refused(data: bytes, reason: str) -> None:
    message = decode_refusal(data)
    assert message.startswith("variable 'value")
    assert reason in message


def test_decoding_imports_nothing() -> None:
    value = {'ekf': DATACLASSES[-1], 'modes': MEMBERS, 'box': Box(Frozen('x'))}
    data = encode_vars(value)
    before = set(sys.modules)
    decoded = decode_vars(data)
    assert set(sys.modules) == before
    assert same(decoded, value)


# --------------------------------------------------------------------------- Time, Duration


@pytest.mark.parametrize('clock_type', list(ClockType), ids=str)
@pytest.mark.parametrize('ns', [0, 1, 1_700_000_000_123_456_789, 2**63 - 1])
def test_time_roundtrip(ns: int, clock_type: ClockType) -> None:
    value = Time(nanoseconds=ns, clock_type=clock_type)
    decoded = roundtrip(value)
    assert type(decoded) is Time
    assert decoded.nanoseconds == ns
    assert decoded.clock_type == clock_type


@pytest.mark.parametrize('ns', [0, -1, 5, -(2**63), 2**63 - 1])
def test_duration_roundtrip(ns: int) -> None:
    decoded = roundtrip(Duration(nanoseconds=ns))
    assert type(decoded) is Duration
    assert decoded.nanoseconds == ns


@pytest.mark.parametrize(
    ('data', 'reason'),
    [
        (ext(EXT_TIME, [-1, 1]), 'malformed rclpy Time payload'),
        (ext(EXT_TIME, [2**63, 1]), 'malformed rclpy Time payload'),
        (ext(EXT_TIME, [True, 1]), 'malformed rclpy Time payload'),
        (ext(EXT_TIME, [1, 1.0]), 'malformed rclpy Time payload'),
        (ext(EXT_TIME, [1, 9]), 'unknown clock type 9'),
        (ext(EXT_TIME, [1]), 'malformed rclpy Time payload'),
        (ext(EXT_DURATION, 2**63), 'malformed rclpy Duration payload'),
        (ext(EXT_DURATION, encode(-(2**63) - 1)), 'malformed rclpy Duration payload'),
        (ext(EXT_DURATION, 2**64 - 1), 'malformed rclpy Duration payload'),
        (ext(EXT_DURATION, 1.5), 'malformed rclpy Duration payload'),
        (ext(EXT_DURATION, [1]), 'malformed rclpy Duration payload'),
    ],
)
def test_bad_time_is_refused(data: bytes, reason: str) -> None:
    assert reason in decode_refusal(data)


def test_builtin_interfaces_messages_are_ros_messages() -> None:
    from builtin_interfaces.msg import Duration as DurationMsg
    from builtin_interfaces.msg import Time as TimeMsg

    value = [TimeMsg(sec=5, nanosec=7), DurationMsg(sec=-1, nanosec=3)]
    assert same(roundtrip(value), value)


# --------------------------------------------------------------------------- deque, OrderedDict


@pytest.mark.parametrize(
    'value',
    [
        deque(),
        deque(maxlen=0),
        deque([1, (2, 3), 'x']),
        deque([1.0, 2.0], maxlen=2),
        deque([(1, np.float32(2))], maxlen=100),
        deque([deque([1], maxlen=1)]),
    ],
    ids=repr,
)
def test_deque_roundtrip(value: deque[object]) -> None:
    decoded = roundtrip(value)
    assert type(decoded) is deque
    assert decoded.maxlen == value.maxlen
    assert same(decoded, value)


def test_ordered_dict_roundtrip() -> None:
    value = OrderedDict([('z', 1), ((1, 2), OrderedDict(a=deque([1]))), (Mode.RUN, None)])
    value.move_to_end('z')
    decoded = roundtrip(value)
    assert type(decoded) is OrderedDict
    assert same(decoded, value)
    assert list(decoded) == list(value)


@pytest.mark.parametrize(
    ('data', 'reason'),
    [
        (ext(EXT_DEQUE, [2, [1, 2, 3]]), 'malformed deque payload'),
        (ext(EXT_DEQUE, [-1, []]), 'malformed deque payload'),
        (ext(EXT_DEQUE, [2**64 - 1, []]), 'malformed deque payload'),
        (ext(EXT_DEQUE, ['3', []]), 'malformed deque payload'),
        (ext(EXT_DEQUE, [None, 'ab']), 'malformed deque payload'),
        (ext(EXT_DEQUE, [None]), 'malformed deque payload'),
        (ext(EXT_ORDEREDDICT, [1, 2]), 'malformed OrderedDict payload'),
    ],
)
def test_bad_deque_and_ordered_dict_are_refused(data: bytes, reason: str) -> None:
    assert reason in decode_refusal(data)


def test_deque_and_ordered_dict_paths() -> None:
    assert refusal(deque([1, Custom()]), name='h').startswith("variable 'h'[1]: ")
    assert refusal(OrderedDict(k=[Custom()]), name='o').startswith("variable 'o'['k'][0]: ")


# --------------------------------------------------------------------------- refusals


class MyNode(rclpy.node.Node):
    pass


ROS_ENTITIES = [
    rclpy.publisher.Publisher,
    rclpy.subscription.Subscription,
    rclpy.timer.Timer,
    rclpy.client.Client,
    rclpy.service.Service,
    rclpy.node.Node,
    MyNode,
]


@pytest.mark.parametrize('cls', ROS_ENTITIES, ids=lambda c: c.__name__)
def test_ros_entities_are_refused(cls: type) -> None:
    # object.__new__: the real class, without creating a ROS participant.
    label = f'{cls.__module__}.{cls.__qualname__}'
    assert refusal(object.__new__(cls), name='pub') == (
        f"variable 'pub': cannot checkpoint a value of type {label} (a ROS entity, not state)"
    )


@pytest.mark.parametrize(
    'make_value',
    [Future, ReentrantCallbackGroup, lambda: RcutilsLogger('rory_test')],
    ids=['future', 'callback-group', 'logger'],
)
def test_other_rclpy_objects_are_refused(make_value: Any) -> None:
    assert refusal(make_value()).endswith('(a ROS entity, not state)')


def generator() -> Any:
    yield 1


async def coroutine() -> None:
    pass


NOT_STATE = [
    (threading.Lock, '_thread.lock', 'a lock or other thread synchronization object, not state'),
    (threading.RLock, '_thread.RLock', 'a lock or other thread synchronization object, not state'),
    (threading.Condition, 'threading.Condition', 'a lock or other thread synchronization'),
    (threading.Semaphore, 'threading.Semaphore', 'a lock or other thread synchronization'),
    (threading.BoundedSemaphore, 'threading.BoundedSemaphore', 'a lock or other thread'),
    (threading.Event, 'threading.Event', 'a lock or other thread synchronization object'),
    (lambda: threading.Barrier(1), 'threading.Barrier', 'a lock or other thread sync'),
    (lambda: threading.Thread(target=print), 'threading.Thread', 'a thread, not state'),
    (lambda: threading.Timer(1, print), 'threading.Timer', 'a thread, not state'),
    (io.BytesIO, '_io.BytesIO', 'an open file or stream, not state'),
    (io.StringIO, '_io.StringIO', 'an open file or stream, not state'),
    (generator, 'generator', 'a generator or coroutine, not state'),
    (lambda: iter([]), 'list_iterator', 'an iterator, not state'),
    (lambda: map(str, []), 'map', 'an iterator, not state'),
    (lambda: lambda: None, 'function', 'a function or method: code, not state'),
    (lambda: function, 'function', 'a function or method: code, not state'),
    (lambda: print, 'builtin_function_or_method', 'a function or method: code, not state'),
    (lambda: (1).__add__, 'method-wrapper', 'a function or method: code, not state'),
    (lambda: Cached(1).__repr__, 'method', 'a function or method: code, not state'),
    (lambda: [].append, 'builtin_function_or_method', 'a function or method'),
    (lambda: functools.partial(print), 'functools.partial', 'a function or method'),
    (lambda: sys, 'module', 'a module: code, not state'),
    (lambda: Custom, 'type', f'the class {HERE}.Custom itself: a class is code, not state'),
    (lambda: Mode, 'enum.EnumType', f'the class {HERE}.Mode itself: a class is code'),
    (lambda: Plain, 'type', f'the class {HERE}.Plain itself: a class is code, not state'),
    (lambda: collections.defaultdict(list), 'collections.defaultdict', 'its default_factory'),
    (collections.Counter, 'collections.Counter', 'a subclass of dict, which would come back'),
    (lambda: PointTuple(1), f'{HERE}.PointTuple', 'a subclass of tuple, which would'),
    (lambda: np.ma.masked_array([1]), 'numpy.ma.MaskedArray', 'a subclass of numpy.ndarray'),
    (Custom, f'{HERE}.Custom', 'a plain object; make its class a dataclass to checkpoint it'),
]


@pytest.mark.parametrize(
    ('make_value', 'label', 'hint'), NOT_STATE, ids=[label for _, label, _ in NOT_STATE]
)
def test_what_is_not_state_is_refused_in_plain_words(
    make_value: Any, label: str, hint: str
) -> None:
    message = refusal(make_value(), name='thing')
    assert message.startswith(f"variable 'thing': cannot checkpoint a value of type {label} (")
    assert hint in message
    assert message.endswith(')')


def test_coroutine_is_refused() -> None:
    value = coroutine()
    try:
        assert 'a generator or coroutine, not state' in refusal(value)
    finally:
        value.close()


def test_open_file_and_socket_are_refused_in_plain_words(tmp_path: Any) -> None:
    with (tmp_path / 'f').open('w') as stream:
        assert refusal(stream, name='log') == (
            "variable 'log': cannot checkpoint a value of type _io.TextIOWrapper"
            ' (an open file or stream, not state)'
        )
    with (tmp_path / 'f').open('rb') as raw:
        assert refusal(raw).endswith('(an open file or stream, not state)')
    with socket.socket() as sock:
        assert refusal(sock, name='sock') == (
            "variable 'sock': cannot checkpoint a value of type socket.socket"
            ' (a socket, not state)'
        )


def test_values_without_a_hint_keep_the_plain_message() -> None:
    assert refusal(object()) == "variable 'value': cannot checkpoint a value of type object"
    assert refusal(1j) == "variable 'value': cannot checkpoint a value of type complex"


# --------------------------------------------------------------------------- property tests

hashables = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=False)
    | st.text(max_size=6)
    | st.sampled_from(MEMBERS),
    lambda children: st.lists(children, max_size=3).map(tuple)
    | st.frozensets(children, max_size=3)
    | st.builds(Frozen, children, children)
    | st.builds(FrozenSlotted, children, children),
    max_leaves=6,
)

times = st.builds(
    lambda ns, clock: Time(nanoseconds=ns, clock_type=clock),
    st.integers(0, 2**63 - 1),
    st.sampled_from(list(ClockType)),
)
durations = st.integers(-(2**63), 2**63 - 1).map(lambda ns: Duration(nanoseconds=ns))

leaves = (
    hashables
    | st.floats()
    | st.binary(max_size=8).map(bytearray)
    | st.lists(st.floats(width=32), max_size=4).map(lambda xs: np.array(xs, dtype='<f4'))
    | st.integers(-(2**31), 2**31 - 1).map(np.int32)
    | st.builds(Int64, data=st.integers(-(2**63), 2**63 - 1))
    | times
    | durations
)


def deques(children: st.SearchStrategy[object]) -> st.SearchStrategy[deque[object]]:
    return st.builds(
        lambda items, slack: deque(items, maxlen=None if slack is None else len(items) + slack),
        st.lists(children, max_size=4),
        st.none() | st.integers(0, 3),
    )


state_values = st.recursive(
    leaves,
    lambda children: st.lists(children, max_size=4)
    | st.lists(children, max_size=4).map(tuple)
    | st.dictionaries(hashables, children, max_size=4)
    | st.dictionaries(hashables, children, max_size=4).map(OrderedDict)
    | deques(children)
    | st.builds(Plain, children, children)
    | st.builds(Slotted, children, children)
    | st.builds(Frozen, children, children)
    | st.builds(Child, children, children, children)
    | st.builds(Holder.Cell, children, st.sampled_from(list(Holder.Phase)))
    | st.builds(Box, children),
    max_leaves=20,
)


@settings(max_examples=examples(300), deadline=None)
@given(state_values)
def test_property_roundtrip_of_state_types(value: object) -> None:
    assert same(roundtrip(value), value)


@settings(max_examples=examples(100), deadline=None)
@given(st.dictionaries(st.text(max_size=8), state_values, max_size=4))
def test_property_vars_roundtrip_of_state_types(variables: dict[str, object]) -> None:
    assert same(decode_vars(encode_vars(variables)), variables)


NEW_CODES = [EXT_ENUM, EXT_DATACLASS, EXT_TIME, EXT_DURATION, EXT_DEQUE, EXT_ORDEREDDICT]


@settings(max_examples=examples(500), deadline=None)
@given(st.binary(max_size=64), st.sampled_from(NEW_CODES))
def test_fuzz_random_payloads_of_new_types(payload: bytes, code: int) -> None:
    with contextlib.suppress(CodecError):
        decode(ext(code, payload))


names = st.sampled_from(
    [HERE, 'collections', 'enum', 'sys', 'builtins', 'no_such_module_rory', '', 'a.b', 1, None]
)
qualnames = st.sampled_from(
    ['Mode', 'Perm', 'Bits', 'Holder.Phase', 'Holder.Cell', 'Plain', 'Frozen', 'Slotted',
     'Instrumented', 'OrderedDict', 'Enum', 'Flag', 'modules', 'Holder', 'x.y', '', 3]
)  # fmt: skip
keys = st.one_of(
    st.text(max_size=8),
    st.integers(-(2**63), 2**64 - 1),
    st.none(),
    st.sampled_from(['RUN', 'R', 'IDLE']),
)


@settings(max_examples=examples(500), deadline=None)
@given(names, qualnames, keys)
def test_fuzz_structured_enum_payloads(module: object, qualname: object, key: object) -> None:
    with contextlib.suppress(CodecError):
        assert isinstance(decode(ext(EXT_ENUM, [module, qualname, key])), enum.Enum)


@settings(max_examples=examples(300), deadline=None)
@given(names, qualnames, st.dictionaries(st.text(max_size=3) | st.sampled_from('xyab'), keys))
def test_fuzz_structured_dataclass_payloads(
    module: object, qualname: object, fields: dict[str, object]
) -> None:
    code_calls.clear()
    with contextlib.suppress(CodecError):
        assert dataclasses.is_dataclass(decode(ext(EXT_DATACLASS, [module, qualname, fields])))
    assert not code_calls


RICH_STATE: dict[str, object] = {
    'ekf': DATACLASSES[-1],
    'modes': [Mode.RUN, Level.HIGH, Colour.RED, Perm.R | Perm.X, Holder.Phase.ONE],
    'frozen': {FrozenSlotted(1): Frozen('a', (Bits.A | Bits.C,))},
    'stamp': Time(nanoseconds=99, clock_type=ClockType.STEADY_TIME),
    'age': Duration(nanoseconds=-5),
    'history': deque([OrderedDict(a=1), OrderedDict(b=(2,))], maxlen=4),
}


@pytest.mark.parametrize('decoder', [decode, decode_vars])
def test_every_truncation_raises_codec_error(decoder: Any) -> None:
    data = encode_vars(RICH_STATE) if decoder is decode_vars else encode(RICH_STATE)
    assert same(decoder(data), RICH_STATE)
    for length in range(len(data)):
        with pytest.raises(CodecError):
            decoder(data[:length])


def test_every_byte_flip_decodes_or_raises_codec_error() -> None:
    data = bytearray(encode(RICH_STATE))
    code_calls.clear()
    for index in range(len(data)):
        damaged = bytearray(data)
        damaged[index] ^= 0xFF
        with contextlib.suppress(CodecError):
            decode(bytes(damaged))
    assert not code_calls


# --------------------------------------------------------------------------- speed


def best_of(runs: int, action: Any) -> float:
    action()  # warm up
    best = math.inf
    for _ in range(runs):
        start = time.perf_counter()
        action()
        best = min(best, time.perf_counter() - start)
    return best


def test_state_types_are_fast_enough() -> None:
    members = [Mode.RUN, Level.LOW, Perm.R | Perm.W] * 1000
    cells = [Holder.Cell(float(i), Holder.Phase.TWO) for i in range(1000)]
    members_s = best_of(5, lambda: decode(encode(members)))
    cells_s = best_of(5, lambda: decode(encode(cells)))
    print(f'3000 Enum members: {members_s * 1e3:.2f} ms; 1000 dataclasses: {cells_s * 1e3:.2f} ms')
    assert members_s < 0.5
    assert cells_s < 0.5
