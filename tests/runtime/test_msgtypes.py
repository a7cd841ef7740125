"""Tests of message classes by name and messages built from mappings."""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from geometry_msgs.msg import Twist
from sensor_msgs.msg import LaserScan
from std_msgs.msg import Bool, Int64

from rory_runtime.errors import RoryError
from rory_runtime.msgtypes import (
    MessageTypeError,
    build_message,
    get_message_class,
    message_type_name,
    type_name_of,
)


def test_get_message_class_std_msgs_int64() -> None:
    assert get_message_class('std_msgs/msg/Int64') is Int64


def test_get_message_class_sensor_msgs_laser_scan() -> None:
    assert get_message_class('sensor_msgs/msg/LaserScan') is LaserScan


def test_message_type_error_is_a_rory_error() -> None:
    assert issubclass(MessageTypeError, RoryError)


@pytest.mark.parametrize(
    'name',
    [
        pytest.param('../x/msg/Y', id='path-traversal'),
        pytest.param('../../etc/msg/Passwd', id='path-traversal-2'),
        pytest.param('std_msgs/srv/Empty', id='service'),
        pytest.param('std_msgs/action/Int64', id='action'),
        pytest.param('std_msgs/msg/int64', id='lowercase-class'),
        pytest.param('Std_msgs/msg/Int64', id='uppercase-package'),
        pytest.param('std_msgs.msg.Int64', id='dotted'),
        pytest.param('std_msgs/Int64', id='no-msg-part'),
        pytest.param('/std_msgs/msg/Int64', id='leading-slash'),
        pytest.param('std_msgs/msg/Int64/x', id='extra-part'),
        pytest.param('std_msgs/msg/', id='no-class'),
        pytest.param('', id='empty'),
        pytest.param('std_msgs/msg/Int_64', id='underscore-in-class'),
        pytest.param('std-msgs/msg/Int64', id='dash-in-package'),
        pytest.param('os.path/msg/Join', id='dotted-package'),
    ],
)
def test_malformed_names_are_refused_before_any_import(name: str) -> None:
    before = set(sys.modules)
    with pytest.raises(MessageTypeError, match='not a message type name'):
        get_message_class(name)
    assert set(sys.modules) == before


def test_name_with_trailing_newline_is_refused() -> None:
    """'$' also matches before a final newline; the name itself is still malformed."""
    with pytest.raises(MessageTypeError):
        get_message_class('std_msgs/msg/Int64\n')


@pytest.mark.parametrize('name', ['os/msg/Path', 'sys/msg/Path'])
def test_stdlib_module_as_package_is_refused(name: str) -> None:
    with pytest.raises(MessageTypeError, match='not installed'):
        get_message_class(name)
    package = name.split('/')[0]
    assert f'{package}.msg' not in sys.modules


def test_uninstalled_package_is_refused_and_not_imported() -> None:
    package = 'rory_no_such_package_xyz'
    with pytest.raises(MessageTypeError, match='not installed'):
        get_message_class(f'{package}/msg/Thing')
    assert package not in sys.modules
    assert f'{package}.msg' not in sys.modules


def test_unknown_message_of_installed_package_is_refused() -> None:
    with pytest.raises(MessageTypeError, match='not a message of package'):
        get_message_class('std_msgs/msg/NoSuchMessage')


@pytest.fixture
def fake_packages(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """Two importable packages that are not ROS message packages; each records its import."""
    marker = tmp_path / 'imported.txt'
    bogus = tmp_path / 'rorytest_bogus_pkg'
    bogus.mkdir()
    (bogus / '__init__.py').write_text(
        f'open({str(marker)!r}, "a").write("rorytest_bogus_pkg\\n")\n'
    )
    fake = tmp_path / 'rorytest_fake_msgs'
    (fake / 'msg').mkdir(parents=True)
    (fake / '__init__.py').write_text('')
    (fake / 'msg' / '__init__.py').write_text('class Fake:\n    pass\n\nNumber = 5\n')
    # what rosidl generates next to a message package; get_message_class looks for it on disk
    (fake / 'rorytest_fake_msgs_s__rosidl_typesupport_c.so').write_bytes(b'')
    monkeypatch.syspath_prepend(str(tmp_path))
    yield marker
    for name in list(sys.modules):
        if name.startswith(('rorytest_bogus_pkg', 'rorytest_fake_msgs')):
            del sys.modules[name]


def test_non_message_attribute_is_refused(fake_packages: Path) -> None:
    for name in ('rorytest_fake_msgs/msg/Fake', 'rorytest_fake_msgs/msg/Number'):
        with pytest.raises(MessageTypeError, match='not a message of package'):
            get_message_class(name)


def test_installed_non_ros_package_is_not_imported(fake_packages: Path) -> None:
    """A name read from a config may only import ``<package>.msg``: a package without one
    must not have its code run (think 'antigravity/msg/X')."""
    with pytest.raises(MessageTypeError):
        get_message_class('rorytest_bogus_pkg/msg/Thing')
    assert 'rorytest_bogus_pkg' not in sys.modules
    assert not fake_packages.exists(), 'the package __init__ ran'


def test_message_type_name_recognises_only_message_classes() -> None:
    assert message_type_name(Int64) == 'std_msgs/msg/Int64'
    assert message_type_name(Int64()) is None
    assert message_type_name(int) is None
    assert message_type_name(None) is None


# --------------------------------------------------------------------------- build_message


def test_build_message_sets_nested_fields_from_mapping() -> None:
    msg = build_message('geometry_msgs/msg/Twist', {'linear': {'x': 1.0}, 'angular': {'z': -0.5}})
    assert isinstance(msg, Twist)
    assert (msg.linear.x, msg.linear.y, msg.linear.z) == (1.0, 0.0, 0.0)
    assert (msg.angular.x, msg.angular.y, msg.angular.z) == (0.0, 0.0, -0.5)


def test_build_message_with_no_fields_is_default() -> None:
    assert build_message('std_msgs/msg/Bool', {}) == Bool()


def test_build_message_top_level_scalar() -> None:
    msg = build_message('std_msgs/msg/Bool', {'data': True})
    assert msg == Bool(data=True)


def test_build_message_unknown_field_names_its_path() -> None:
    with pytest.raises(MessageTypeError) as info:
        build_message('geometry_msgs/msg/Twist', {'linear': {'w': 1.0}})
    text = str(info.value)
    assert 'geometry_msgs/msg/Twist.linear.w' in text
    assert 'no such field' in text
    assert 'x, y, z' in text


def test_build_message_unknown_top_level_field_names_its_path() -> None:
    with pytest.raises(MessageTypeError, match=r'std_msgs/msg/Bool\.value: no such field'):
        build_message('std_msgs/msg/Bool', {'value': True})


def test_build_message_wrong_typed_value_names_its_path() -> None:
    with pytest.raises(MessageTypeError) as info:
        build_message('geometry_msgs/msg/Twist', {'linear': {'x': 'fast'}})
    text = str(info.value)
    assert 'geometry_msgs/msg/Twist.linear.x' in text
    assert "'fast'" in text
    assert 'double' in text


def test_build_message_out_of_range_value_names_its_path() -> None:
    with pytest.raises(MessageTypeError, match=r'std_msgs/msg/Int64\.data'):
        build_message('std_msgs/msg/Int64', {'data': 2**70})


def test_build_message_mapping_for_scalar_field_is_refused() -> None:
    with pytest.raises(MessageTypeError, match=r'std_msgs/msg/Bool\.data: is not a message'):
        build_message('std_msgs/msg/Bool', {'data': {'x': 1}})


def test_build_message_path_is_prefixed_with_where() -> None:
    with pytest.raises(MessageTypeError) as info:
        build_message('geometry_msgs/msg/Twist', {'linear': {'q': 1}}, where='safe_state[0].hold')
    assert str(info.value).startswith('safe_state[0].hold.linear.q:')


def test_build_message_unknown_type_is_refused() -> None:
    with pytest.raises(MessageTypeError):
        build_message('std_msgs/msg/Nope', {})


# --------------------------------------------------------------------------- type_name_of


@pytest.mark.parametrize(
    ('cls', 'name'),
    [
        (Int64, 'std_msgs/msg/Int64'),
        (LaserScan, 'sensor_msgs/msg/LaserScan'),
        (Twist, 'geometry_msgs/msg/Twist'),
    ],
)
def test_type_name_of(cls: type, name: str) -> None:
    assert type_name_of(cls) == name
    assert get_message_class(type_name_of(cls)) is cls
