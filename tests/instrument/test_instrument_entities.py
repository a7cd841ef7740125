"""Node shapes RORY refuses are refused by rory-instrument with file:line:col: two subscriptions
to one literal topic in a node, and async def callbacks."""

from __future__ import annotations

import textwrap

import libcst as cst
import pytest
from libcst.metadata import MetadataWrapper

from rory_instrument.entities import check_entities
from rory_instrument.errors import SourceError


def check(source: str, scopes: list[str | None]) -> None:
    wrapper = MetadataWrapper(cst.parse_module(textwrap.dedent(source)))
    check_entities(wrapper, 'node.py', scopes)


def refusal(source: str, scopes: list[str | None]) -> SourceError:
    with pytest.raises(SourceError) as caught:
        check(source, scopes)
    return caught.value


def test_distinct_topics_and_plain_callbacks_pass() -> None:
    check('''
        class N(Node):
            def __init__(self):
                self.create_subscription(Int64, '/a', self.on_a, 10)
                self.create_subscription(Int64, topic='/b', callback=self.on_b, qos_profile=10)
                self.create_timer(0.1, self.tick)
                self.create_service(SetBool, 'go', self.go)

            def on_a(self, msg): ...
            def on_b(self, msg): ...
            def tick(self): ...
            def go(self, req, resp): ...
    ''', ['N'])


def test_a_second_subscription_to_one_topic_is_refused_where_it_is() -> None:
    err = refusal('''
        class N(Node):
            def __init__(self):
                self.create_subscription(Int64, '/scan', self.a, 10)
                self.make()

            def make(self):
                node = self
                node.create_subscription(LaserScan, topic='/scan', callback=self.b,
                                         qos_profile=10)
    ''', ['N'])
    assert (err.path, err.line, err.col) == ('node.py', 9, 9)
    assert err.message.startswith('second subscription to /scan (the first is at line 4)')


def test_the_same_topic_in_two_node_classes_is_two_nodes() -> None:
    check('''
        class A(Node):
            def __init__(self):
                self.create_subscription(Int64, '/x', self.cb, 10)

        class B(Node):
            def __init__(self):
                self.create_subscription(Int64, '/x', self.cb, 10)
    ''', ['A', 'B'])


def test_only_listed_nodes_are_checked() -> None:
    check('''
        class Tool(Node):
            def __init__(self):
                self.create_subscription(Int64, '/x', self.cb, 10)
                self.create_subscription(Int64, '/x', self.cb, 10)
    ''', ['Other'])


def test_computed_topics_are_left_to_the_runtime() -> None:
    check('''
        class N(Node):
            def __init__(self):
                for topic in ('/x', '/x'):
                    self.create_subscription(Int64, topic, self.cb, 10)
    ''', ['N'])


@pytest.mark.parametrize(('call', 'what'), [
    ("self.create_subscription(Int64, '/x', self.cb, 10)", 'subscription'),
    ('self.create_timer(0.5, callback=self.cb)', 'timer'),
    ("self.create_service(Trigger, 'go', self.cb)", 'service'),
])
def test_an_async_method_as_callback_is_refused(call: str, what: str) -> None:
    err = refusal(f'''
        class N(Node):
            def __init__(self):
                {call}

            async def cb(self, *args):
                return None
    ''', ['N'])
    assert err.line == 4
    assert err.message.startswith(f'self.cb is an async def callback (of a {what})')


def test_nested_classes_are_their_own_scope() -> None:
    check('''
        class Outer(Node):
            def __init__(self):
                self.create_subscription(Int64, '/x', self.cb, 10)

            class Inner(Node):
                def __init__(self):
                    self.create_subscription(Int64, '/x', self.cb, 10)

                def cb(self, msg): ...

            def cb(self, msg): ...
    ''', ['Outer', 'Outer.Inner'])


def test_an_async_method_of_another_class_is_not_this_ones() -> None:
    check('''
        class Helper:
            async def cb(self, msg): ...

        class N(Node):
            def __init__(self):
                self.create_subscription(Int64, '/x', self.cb, 10)

            def cb(self, msg): ...
    ''', ['N'])


def test_a_node_written_as_functions_is_checked_at_module_level() -> None:
    err = refusal('''
        async def on_number(msg):
            pass

        def main():
            node = rclpy.create_node('n')
            node.create_subscription(Int64, '/numbers', on_number, 10)
    ''', [None])
    assert err.line == 7
    assert err.message.startswith('on_number is an async def callback (of a subscription)')


def test_checking_twice_gives_the_same_answer() -> None:
    source = '''
        class N(Node):
            def __init__(self):
                self.create_subscription(Int64, '/x', self.cb, 10)
    '''
    check(source, ['N', 'N'])
    check(source, ['N'])
