"""Tests of the checkpoint value codec."""

from __future__ import annotations

import collections
import contextlib
import io
import math
import socket
import sys
import threading
import time
from typing import Any

import msgpack
import numpy as np
import pytest
from geometry_msgs.msg import Point, Pose, Quaternion
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_budget import examples
from rclpy.node import Node
from rclpy.serialization import serialize_message
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Header, Int64, String
from std_srvs.srv import Trigger

from rory_runtime.codec import (
    EXT_BIGINT,
    EXT_NDARRAY,
    EXT_NPSCALAR,
    EXT_ROSMSG,
    EXT_SET,
    EXT_TUPLE,
    decode,
    decode_vars,
    encode,
    encode_vars,
)
from rory_runtime.errors import CodecError


def same(a: object, b: object) -> bool:
    """Equal in value *and* type, all the way down; nan equals nan, -0.0 differs from 0.0."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        assert isinstance(b, float)
        if math.isnan(a):
            return math.isnan(b)
        return a == b and math.copysign(1, a) == math.copysign(1, b)
    if isinstance(a, list | tuple):
        assert isinstance(b, list | tuple)
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
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
    return a == b


def roundtrip(value: object) -> object:
    return decode(encode(value))


def ext(code: int, payload: object) -> bytes:
    """Encoding of an extension value with a hand-made payload."""
    raw = payload if isinstance(payload, bytes) else msgpack.packb(payload, use_bin_type=True)
    return bytes(msgpack.packb(msgpack.ExtType(code, raw)))


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize(
    'value',
    [
        None,
        True,
        False,
        0,
        -1,
        2**63 - 1,
        -(2**63),
        2**64 - 1,
        2**64,
        -(2**63) - 1,
        2**200,
        -(2**200) + 7,
        10**100,
        1.5,
        float('inf'),
        float('-inf'),
        float('nan'),
        -0.0,
        0.0,
        '',
        'héllo wörld ✓',
        'lone surrogate \ud800',
        b'',
        b'\x00\xff',
        bytearray(),
        bytearray(b'\x00abc'),
        [],
        [1, 'a', None],
        (),
        (1,),
        (1, (2, (3, [4, (5,)]))),
        {},
        {'a': 1},
        {1: 'one', (1, 2): 'pair', None: 0, b'k': 1, 2.5: 'x', False: 'no'},
        {(1, ('nested', 2)): [(), ()]},
        {frozenset({1, 2}): 'fs'},
        set(),
        {1, 'a', (2, 3), None},
        frozenset(),
        frozenset({1, frozenset({2})}),
        [bytearray(b'x'), (bytearray(b'y'),)],
    ],
    ids=lambda v: type(v).__name__ if isinstance(v, set | frozenset | dict) else repr(v),
)  # (a set's repr depends on str hash randomization, which differs between xdist workers)
def test_roundtrip_exact(value: object) -> None:
    assert same(roundtrip(value), value)


def test_dict_insertion_order_is_kept() -> None:
    value = {'z': 1, 'a': 2, 3: 3, (0,): 4, 'm': 5}
    assert list(roundtrip(value)) == list(value)  # type: ignore[call-overload]


def test_tuple_stays_tuple_at_any_depth() -> None:
    value = [{'k': ((1, 2), [3, (4,)])}]
    decoded = roundtrip(value)
    assert same(decoded, value)
    assert isinstance(decoded, list)
    inner = decoded[0]['k']
    assert type(inner) is tuple
    assert type(inner[0]) is tuple
    assert type(inner[1][1]) is tuple


@pytest.mark.parametrize(
    'dtype',
    [
        'bool', 'int8', 'int16', 'int32', 'int64', 'uint8', 'uint16', 'uint32', 'uint64',
        'float16', 'float32', 'float64', 'longdouble', 'complex64', 'complex128',
        '>i2', '>i4', '>u8', '>f4', '>f8', '>c16', '<f8',
    ],
)  # fmt: skip
@pytest.mark.parametrize('shape', [(), (0,), (5,), (3, 0), (2, 3, 4)])
def test_ndarray_roundtrip(dtype: str, shape: tuple[int, ...]) -> None:
    rng = np.random.default_rng(1)
    array = np.asarray(rng.random(shape) * 100).astype(dtype)
    decoded = roundtrip(array)
    assert isinstance(decoded, np.ndarray)
    assert same(decoded, array)
    assert decoded.dtype == np.dtype(dtype)
    assert decoded.dtype.byteorder == np.dtype(dtype).byteorder
    assert decoded.flags.writeable
    assert decoded.flags.owndata


def test_ndarray_special_floats_keep_their_bits() -> None:
    array = np.array([np.nan, np.inf, -np.inf, -0.0, 0.0, 1e-310])
    assert roundtrip(array).tobytes() == array.tobytes()  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    'make',
    [
        lambda a: a[::2],
        lambda a: a.T,
        lambda a: a[:, 1],
        lambda a: np.asfortranarray(a),
        lambda a: a[::-1, ::3],
    ],
    ids=['stride', 'transpose', 'column', 'fortran', 'negative-stride'],
)
def test_ndarray_non_contiguous(make: Any) -> None:
    array = make(np.arange(60, dtype=np.float64).reshape(6, 10))
    decoded = roundtrip(array)
    assert isinstance(decoded, np.ndarray)
    np.testing.assert_array_equal(decoded, array)
    assert decoded.dtype == array.dtype


def test_decoded_ndarray_is_not_a_view_of_the_buffer() -> None:
    data = encode(np.arange(4, dtype=np.int32))
    decoded = decode(data)
    assert isinstance(decoded, np.ndarray)
    decoded[0] = 99  # would raise if it were a read-only view of data
    assert decoded.base is None


@pytest.mark.parametrize(
    'scalar',
    [
        np.float32(1.5),
        np.float64(-0.0),
        np.float16(3),
        np.int8(-5),
        np.int64(2**62),
        np.uint64(2**64 - 1),
        np.bool_(True),
        np.complex64(1 + 2j),
        np.longdouble(1.25),
    ],
    ids=repr,
)
def test_numpy_scalar_keeps_its_type(scalar: np.generic) -> None:
    decoded = roundtrip(scalar)
    assert type(decoded) is type(scalar)
    assert same(decoded, scalar)


def test_numpy_float64_is_not_confused_with_float() -> None:
    # np.float64 subclasses float; it must still come back as np.float64.
    assert type(roundtrip(np.float64(2.5))) is np.float64
    assert type(roundtrip(2.5)) is float


@pytest.mark.parametrize(
    'message',
    [
        Int64(data=-42),
        String(data='hello'),
        Pose(position=Point(x=1.0, y=2.0, z=3.0), orientation=Quaternion(w=1.0)),
        Header(frame_id='map'),
        LaserScan(ranges=[1.0, 2.0, float('inf')], angle_max=3.0),
    ],
    ids=lambda m: type(m).__name__,
)
def test_ros_message_roundtrip(message: object) -> None:
    decoded = roundtrip(message)
    assert type(decoded) is type(message)
    # Field by field: CDR bytes are no fit, their alignment padding is uninitialized memory.
    assert decoded == message


def test_list_of_ros_messages() -> None:
    poses = [Pose(position=Point(x=float(i))) for i in range(5)]
    decoded = roundtrip({'path': poses, 'pair': (Int64(data=1), Int64(data=2))})
    assert isinstance(decoded, dict)
    assert decoded['path'] == poses
    assert all(type(p) is Pose for p in decoded['path'])
    assert decoded['pair'] == (Int64(data=1), Int64(data=2))


def test_vars_roundtrip() -> None:
    values: dict[str, object] = {
        'total': 3.5,
        'count': 7,
        'history': [(1, 2.0), (2, 4.0)],
        'pose': Pose(),
        'grid': np.zeros((2, 2), dtype=np.uint8),
        'seen': {1, 2},
        'big': 2**100,
    }
    decoded = decode_vars(encode_vars(values))
    assert list(decoded) == list(values)
    for name in values:
        assert same(decoded[name], values[name]), name


def test_empty_vars() -> None:
    assert decode_vars(encode_vars({})) == {}


# --------------------------------------------------------------------------- property tests

hashables = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=-(2**130), max_value=2**130)
    | st.floats(allow_nan=False)
    | st.text(max_size=8)
    | st.binary(max_size=8),
    lambda children: st.lists(children, max_size=3).map(tuple)
    | st.frozensets(children, max_size=3),
    max_leaves=8,
)

leaves = (
    hashables
    | st.floats()
    | st.binary(max_size=16).map(bytearray)
    | st.floats(width=32).map(np.float32)
    | st.integers(min_value=-(2**63), max_value=2**63 - 1).map(np.int64)
    | st.lists(st.floats(), max_size=6).map(lambda xs: np.array(xs, dtype='>f8'))
    | st.lists(st.integers(0, 255), max_size=6).map(lambda xs: np.array(xs, dtype=np.uint8))
)

values = st.recursive(
    leaves,
    lambda children: st.lists(children, max_size=4)
    | st.lists(children, max_size=4).map(tuple)
    | st.dictionaries(hashables, children, max_size=4)
    | st.sets(hashables, max_size=4)
    | st.frozensets(hashables, max_size=4),
    max_leaves=25,
)


@settings(max_examples=examples(300), deadline=None)
@given(values)
def test_property_roundtrip(value: object) -> None:
    assert same(roundtrip(value), value)


@settings(max_examples=examples(100), deadline=None)
@given(st.dictionaries(st.text(max_size=10), values, max_size=5))
def test_property_vars_roundtrip(variables: dict[str, object]) -> None:
    decoded = decode_vars(encode_vars(variables))
    assert same(decoded, variables)


@settings(max_examples=examples(1000), deadline=None)
@given(st.binary(max_size=64))
def test_fuzz_random_bytes_decode_or_codec_error(data: bytes) -> None:
    for decoder in (decode, decode_vars):
        with contextlib.suppress(CodecError):
            decoder(data)


@settings(max_examples=examples(300), deadline=None)
@given(
    st.binary(min_size=1, max_size=64),
    st.integers(EXT_TUPLE, 16),  # every extension type the codec knows
)
def test_fuzz_random_extension_payloads(payload: bytes, code: int) -> None:
    with contextlib.suppress(CodecError):
        decode(ext(code, payload))


RICH_VALUE: dict[str, object] = {
    'n': None,
    'ints': [0, -1, 2**70, -(2**70)],
    'floats': (1.5, float('nan'), -0.0),
    'text': 'ü',
    'blob': bytearray(b'ab'),
    'map': {(1, 2): {3, 4}, 'f': frozenset({'x'})},
    'arr': np.arange(6, dtype='>i4').reshape(2, 3),
    'scalar': np.float32(1.5),
    'msg': Int64(data=5),
    'poses': [Pose(), Pose()],
}


@pytest.mark.parametrize('decoder', [decode, decode_vars])
def test_every_truncation_decodes_or_raises_codec_error(decoder: Any) -> None:
    data = encode_vars(RICH_VALUE) if decoder is decode_vars else encode(RICH_VALUE)
    assert same(decoder(data), RICH_VALUE)
    for length in range(len(data)):
        with pytest.raises(CodecError):
            # A strict prefix of a map is never a complete value.
            decoder(data[:length])


def test_every_byte_flip_decodes_or_raises_codec_error() -> None:
    data = bytearray(encode(RICH_VALUE))
    for index in range(len(data)):
        damaged = bytearray(data)
        damaged[index] ^= 0xFF
        with contextlib.suppress(CodecError):
            decode(bytes(damaged))


# --------------------------------------------------------------------------- refusals


class Custom:
    pass


def function() -> None:
    pass


def refusal(value: object, name: str = 'value') -> str:
    with pytest.raises(CodecError) as info:
        encode(value, name=name)
    return str(info.value)


@pytest.mark.parametrize(
    ('value', 'label'),
    [
        (function, 'function'),
        (lambda: None, 'function'),
        (print, 'builtin_function_or_method'),
        (threading.Lock(), '_thread.lock'),
        (threading.Event(), 'threading.Event'),
        (io.BytesIO(), '_io.BytesIO'),
        (Custom(), 'Custom'),
        (collections.defaultdict(list), 'collections.defaultdict'),
        (iter([]), 'list_iterator'),
        ((x for x in ()), 'generator'),
        (sys, 'module'),
        (object(), 'object'),
        (memoryview(b'x'), 'memoryview'),
        (range(3), 'range'),
        (1j, 'complex'),
        (Node.__new__(Node), 'rclpy.node.Node'),
        (Trigger.Request(), 'Trigger_Request'),
        (Int64, 'Metaclass_Int64'),
        (np.datetime64('2020-01-01'), 'numpy.datetime64'),
        (np.str_('x'), 'numpy.str_'),
        (np.ma.masked_array([1, 2]), 'numpy.ma'),
    ],
    ids=lambda v: v if isinstance(v, str) else type(v).__name__,
)
def test_unsupported_value_is_refused_with_its_type(value: object, label: str) -> None:
    message = refusal(value, name='thing')
    assert message.startswith("variable 'thing': cannot checkpoint ")
    assert label in message


def test_open_file_and_socket_are_refused(tmp_path: Any) -> None:
    with (tmp_path / 'f').open('w') as stream:
        assert '_io.TextIOWrapper' in refusal(stream)
    with socket.socket() as sock:
        assert 'socket.socket' in refusal(sock)


@pytest.mark.parametrize(
    ('dtype', 'shown'),
    [(object, 'object'), ('<U3', '<U3'), ('S2', '|S2'), ([('a', 'i4')], "[('a', '<i4')]")],
    ids=['object', 'unicode', 'bytes', 'structured'],
)
def test_non_numeric_arrays_are_refused(dtype: Any, shown: str) -> None:
    message = refusal(np.zeros(2, dtype=dtype), name='arr')
    assert message.startswith("variable 'arr': cannot checkpoint a numpy array of dtype")
    assert shown in message


@pytest.mark.parametrize(
    ('value', 'path'),
    [
        ({'history': [1, 2, 3, threading.Lock()]}, "'history'[3]"),
        ({'cfg': {'gains': [1.0, function]}}, "'cfg'['gains'][1]"),
        ({'cfg': {7: (0, (1, Custom()))}}, "'cfg'[7][1][1]"),
        ({'keys': {'a': 1, (1, Custom()): 2}}, "'keys'.keys()[1][1]"),
        ({'members': {Custom()}}, "'members'{0}"),
        ({'fs': frozenset({(1, Custom())})}, "'fs'{0}[1]"),
        ({'arrays': [np.zeros(1), np.zeros(1, dtype=object)]}, "'arrays'[1]"),
    ],
    ids=lambda v: v if isinstance(v, str) else '',
)
def test_refusal_names_the_path(value: dict[str, object], path: str) -> None:
    with pytest.raises(CodecError) as info:
        encode_vars(value)
    assert str(info.value).startswith(f'variable {path}: cannot checkpoint ')


def test_refusal_uses_the_name_given_to_encode() -> None:
    assert refusal([0, Custom()], name='buf').startswith("variable 'buf'[1]: ")
    assert refusal(Custom()).startswith("variable 'value': ")


def test_vars_name_must_be_str() -> None:
    with pytest.raises(CodecError, match='variable name 3 is not a str'):
        encode_vars({3: 1})  # type: ignore[dict-item]


def test_reference_cycles_are_refused() -> None:
    loop: list[object] = []
    loop.append(loop)
    with pytest.raises(CodecError, match='reference cycle'):
        encode_vars({'loop': loop})
    inner: list[object] = []
    through_tuple = (inner,)
    inner.append(through_tuple)
    with pytest.raises(CodecError, match="variable 't': nested too deeply or contains a ref"):
        encode(through_tuple, name='t')


def test_msgpack_nesting_limit_is_a_codec_error() -> None:
    value: list[object] = []
    for _ in range(600):
        value = [value]
    with pytest.raises(CodecError, match="variable 'value'"):
        encode(value)


# --------------------------------------------------------------------------- bad bytes


def decode_refusal(data: bytes) -> str:
    with pytest.raises(CodecError) as info:
        decode(data)
    return str(info.value)


@pytest.mark.parametrize(
    ('data', 'reason'),
    [
        (b'', 'truncated'),
        (b'\x92\x01', 'truncated'),
        (b'\xc1', 'invalid msgpack format byte'),
        (b'\x01\x02', 'trailing bytes'),
        (b'\x91' * 5000 + b'\x01', 'nested too deeply'),
        (b'\xdd\xff\xff\xff\xff', 'exceeds'),  # array claiming 4G items in 5 bytes
        (b'\xa2\xff\xfe', 'UnicodeDecodeError'),
        (ext(99, b''), 'unknown extension type 99'),
        (ext(0, b''), 'unknown extension type 0'),
        (ext(EXT_TUPLE, {'not': 'a list'}), 'malformed tuple payload'),
        (ext(EXT_SET, [[1]]), "unhashable type: 'list'"),
        (ext(EXT_BIGINT, b''), 'empty big integer'),
        (msgpack.packb({(1,): 1}, use_bin_type=True)[:1] + b'\x91\x01\x01', 'unhashable'),
    ],
    ids=[
        'empty', 'short-array', 'format-byte', 'trailing', 'deep', 'huge-length', 'utf8',
        'ext-99', 'ext-0', 'tuple-payload', 'set-unhashable', 'bigint-empty', 'list-key',
    ],
)  # fmt: skip
def test_bad_bytes_are_refused(data: bytes, reason: str) -> None:
    message = decode_refusal(data)
    assert message.startswith("variable 'value': cannot decode: ")
    assert reason in message


@pytest.mark.parametrize(
    ('payload', 'reason'),
    [
        (['<f8', [2], b'\x00' * 15], 'needs 16 bytes, got 15'),
        (['<f8', [2, 2], b'\x00' * 16], 'needs 32 bytes, got 16'),
        (['<f8', [], b''], 'needs 8 bytes, got 0'),
        (['|O8', [1], b'\x00' * 8], "unsupported numpy dtype '|O8'"),
        (['<U1', [1], b'\x00' * 4], "unsupported numpy dtype '<U1'"),
        (['|V8', [1], b'\x00' * 8], "unsupported numpy dtype '|V8'"),
        (["[('a','<i4')]", [1], b'\x00' * 4], 'unsupported numpy dtype'),
        (['<f8', [-1], b''], 'malformed numpy shape'),
        (['<f8', [True], b'\x00' * 8], 'malformed numpy shape'),
        (['<f8', [1] * 65, b'\x00' * 8], 'malformed numpy shape'),
        (['<f8', [2**40, 2**40], b''], 'needs'),
        (['<f8', [1], 'text'], 'malformed ndarray payload'),
        (['<f8', [1]], 'malformed ndarray payload'),
        ('<f8', 'malformed ndarray payload'),
    ],
)
def test_bad_ndarray_is_refused(payload: object, reason: str) -> None:
    assert reason in decode_refusal(ext(EXT_NDARRAY, payload))


@pytest.mark.parametrize(
    ('payload', 'reason'),
    [
        (['<f4', b'\x00' * 8], 'malformed numpy scalar'),
        (['|O8', b'\x00' * 8], 'unsupported numpy dtype'),
        ([1, b''], 'unsupported numpy dtype 1'),
    ],
)
def test_bad_numpy_scalar_is_refused(payload: object, reason: str) -> None:
    assert reason in decode_refusal(ext(EXT_NPSCALAR, payload))


CDR_INT64 = serialize_message(Int64(data=1))


@pytest.mark.parametrize(
    ('type_name', 'reason'),
    [
        ('os/system', 'bad ROS message type name'),
        ('std_msgs/msg/int64', 'bad ROS message type name'),
        ('std_msgs/srv/Int64', 'bad ROS message type name'),
        ('../std_msgs/msg/Int64', 'bad ROS message type name'),
        ('std_msgs.msg/msg/Int64', 'bad ROS message type name'),
        ('std_msgs/msg/Int64;import os', 'bad ROS message type name'),
        ('std_msgs/msg/Int64\n', 'bad ROS message type name'),
        ('Std_msgs/msg/Int64', 'bad ROS message type name'),
        ('nosuch_msgs/msg/Thing', 'nosuch_msgs/msg/Thing is not installed'),
        ('std_msgs/msg/NoSuchType', 'std_msgs/msg/NoSuchType is not installed'),
        ('std_msgs/msg/Metaclass', 'is not installed'),  # exists in no module
        ('os/msg/Path', 'os/msg/Path is not installed'),
    ],
)
def test_bad_ros_type_name_is_refused(type_name: str, reason: str) -> None:
    modules = set(sys.modules)
    assert reason in decode_refusal(ext(EXT_ROSMSG, [type_name, CDR_INT64]))
    # Nothing new may have been imported because of a name that is not a message type.
    assert not {m for m in set(sys.modules) - modules if not m.startswith('nosuch')}


def test_bad_ros_payload_is_refused() -> None:
    reason = decode_refusal(ext(EXT_ROSMSG, ['std_msgs/msg/Int64', b'\x00\x01']))
    assert 'cannot deserialize ROS message std_msgs/msg/Int64' in reason
    assert 'malformed ROS message payload' in decode_refusal(
        ext(EXT_ROSMSG, ['std_msgs/msg/Int64', 'text'])
    )
    assert 'malformed ROS message payload' in decode_refusal(ext(EXT_ROSMSG, ['a']))


def test_decode_vars_names_the_variable() -> None:
    good = encode_vars({'fine': 1})
    bad = msgpack.packb(
        {'fine': 1, 'pose': msgpack.ExtType(EXT_ROSMSG, msgpack.packb(['x/msg/Y', b'']))}
    )
    assert decode_vars(good) == {'fine': 1}
    with pytest.raises(CodecError, match=r"^variable 'pose': cannot decode: .*x/msg/Y"):
        decode_vars(bad)


@pytest.mark.parametrize(
    ('data', 'message'),
    [
        (msgpack.packb([1, 2]), 'checkpoint variables: cannot decode'),
        (msgpack.packb({1: 2}), 'name of variable #0: is a int, not a str'),
        (msgpack.packb({'a': 1}) + b'\x00', 'checkpoint variables: cannot decode: 1 trailing'),
        (msgpack.packb({'a': 1})[:-1], "variable 'a': cannot decode: truncated"),
        (b'', 'checkpoint variables: cannot decode'),
    ],
    ids=['not-a-map', 'int-name', 'trailing', 'truncated', 'empty'],
)
def test_decode_vars_refusals(data: bytes, message: str) -> None:
    with pytest.raises(CodecError) as info:
        decode_vars(data)
    assert str(info.value).startswith(message)


# --------------------------------------------------------------------------- speed


def test_one_megabyte_array_is_fast() -> None:
    array = np.random.default_rng(0).integers(0, 255, 2**20, dtype=np.uint8)
    roundtrip(array)  # warm up
    best = math.inf
    for _ in range(5):
        start = time.perf_counter()
        decoded = roundtrip(array)
        best = min(best, time.perf_counter() - start)
    assert isinstance(decoded, np.ndarray)
    assert np.array_equal(decoded, array)
    print(f'1 MiB uint8 array encode+decode: {best * 1e3:.2f} ms')
    assert best < 0.05


@pytest.mark.parametrize('bit_generator', ['PCG64', 'PCG64DXSM', 'MT19937', 'Philox', 'SFC64'])
def test_numpy_generator_continues_its_stream_exactly(bit_generator: str) -> None:
    generator = np.random.Generator(getattr(np.random, bit_generator)(7))
    generator.normal(size=5)
    generator.integers(0, 10, size=3, dtype=np.uint32)  # leaves a buffered half word
    restored = decode(encode(generator))
    assert type(restored) is np.random.Generator
    assert type(restored.bit_generator).__name__ == bit_generator
    assert np.array_equal(generator.random(100), restored.random(100))
    assert np.array_equal(generator.integers(0, 10, 9, dtype=np.uint32),
                          restored.integers(0, 10, 9, dtype=np.uint32))


def test_python_random_continues_its_stream_exactly() -> None:
    import random

    generator = random.Random(3)
    generator.gauss(0.0, 1.0)  # leaves a cached gaussian
    restored = decode(encode(generator))
    assert type(restored) is random.Random
    assert [generator.gauss(0, 1) for _ in range(5)] == [restored.gauss(0, 1) for _ in range(5)]


@pytest.mark.parametrize('payload', [
    ['PCG64', {'state': {'state': 1}}],
    ['PCG64', 'not a dict'],
    ['os.system', {}],
    ['MT19937', {'bit_generator': 'MT19937', 'state': {'key': [1, 2], 'pos': 0}}],
    [1, 2],
])
def test_hostile_generator_payload_is_a_codec_error(payload: list[object]) -> None:
    data = msgpack.packb(msgpack.ExtType(15, msgpack.packb(payload)))
    with pytest.raises(CodecError, match='numpy Generator'):
        decode(data)


@pytest.mark.parametrize('state', [[3, [1, 2], None], 'x', [3, list(range(625)), 'gauss']])
def test_hostile_python_random_payload_is_a_codec_error(state: object) -> None:
    data = msgpack.packb(msgpack.ExtType(16, msgpack.packb(state)))
    with pytest.raises(CodecError, match=r'random\.Random'):
        decode(data)


_packable = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats()
    | st.text(max_size=8) | st.binary(max_size=16)
    | st.sampled_from(['PCG64', 'MT19937', '<f8', '|b1', 'std_msgs/msg/Int64', 'os', 'state']),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
        st.text(max_size=6) | st.integers(-3, 3), inner, max_size=4),
    max_leaves=16,
)


@settings(max_examples=examples(500), deadline=None)
@given(_packable, st.integers(EXT_TUPLE, 16))
def test_fuzz_well_formed_msgpack_in_every_extension(payload: object, code: int) -> None:
    # Structured payloads get past the msgpack layer and exercise each type's own checks.
    with contextlib.suppress(CodecError):
        decode(msgpack.packb(msgpack.ExtType(code, msgpack.packb(payload))))
