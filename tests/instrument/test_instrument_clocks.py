"""Clock reads RORY cannot replay are warned about with file:line:col, by qualified name."""

from __future__ import annotations

import textwrap

import libcst as cst
import pytest
from libcst.metadata import MetadataWrapper

from rory_instrument.clocks import WALL_CLOCK_READS, wall_clock_warnings


def warnings(source: str) -> list[str]:
    wrapper = MetadataWrapper(cst.parse_module(textwrap.dedent(source)))
    return list(wall_clock_warnings(wrapper, 'node.py'))


def test_no_clock_read_no_warning() -> None:
    assert warnings('''
        import time
        from rclpy.node import Node

        class N(Node):
            def cb(self, msg):
                self.t = self.get_clock().now()
                start = time.perf_counter()  # a duration, not a time: no warning
                time.sleep(0.1)
    ''') == []


def test_a_direct_read_is_named_with_its_position() -> None:
    assert warnings('''
        import time

        def cb(msg):
            return time.time()
    ''') == ['node.py:5:12: warning: time.time() is read directly; RORY cannot replay it '
             'after a crash (in a callback, read self.get_clock().now())']


@pytest.mark.parametrize(('imports', 'call', 'name'), [
    ('import time as t', 't.monotonic()', 'time.monotonic'),
    ('from time import time_ns as now_ns', 'now_ns()', 'time.time_ns'),
    ('from datetime import datetime', 'datetime.now()', 'datetime.datetime.now'),
    ('import datetime', 'datetime.datetime.utcnow()', 'datetime.datetime.utcnow'),
    ('from datetime import date', 'date.today()', 'datetime.date.today'),
])
def test_aliases_are_found_by_qualified_name(imports: str, call: str, name: str) -> None:
    assert name in WALL_CLOCK_READS
    found = warnings(f'{imports}\nx = {call}\n')
    assert len(found) == 1
    assert found[0].startswith(f'node.py:2:5: warning: {name}() ')


def test_reads_in_nested_functions_lambdas_and_methods_are_all_found() -> None:
    found = warnings('''
        import time

        class N:
            def cb(self, msg):
                def inner():
                    return time.monotonic_ns()
                self.f = lambda: time.time()
                return inner()
    ''')
    assert [w.split(': ')[0] for w in found] == ['node.py:7:20', 'node.py:8:26']


def test_a_local_function_named_time_is_not_a_clock() -> None:
    assert warnings('''
        def time():
            return 0

        x = time()
    ''') == []
