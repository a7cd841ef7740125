"""The checks before a rewrite: attribute paths, module vars, values that are not state.

Every error is asserted in full, ``file:line:col: message``; sources are small enough to
count their lines by eye.
"""

from __future__ import annotations

import textwrap

import pytest

from rory_instrument.config import KeyVars, Mark, NodeSpec
from rory_instrument.errors import ConfigError, InstrumentError, SourceError
from rory_instrument.transform import instrument_source

FILE = 'node.py'


def code(text: str) -> str:
    return textwrap.dedent(text).lstrip('\n')


def spec(
    class_name: str | None = None, vars: tuple[str, ...] = (), module_vars: tuple[str, ...] = ()
) -> KeyVars:
    marks = {'': Mark(2, 5), 'class': Mark(3, 12)}
    marks.update({f'module_vars[{i}]': Mark(5, 20 + 10 * i) for i in range(len(module_vars))})
    node = NodeSpec(0, FILE, class_name, vars, module_vars=module_vars, marks=marks)
    return KeyVars('keyvars.yaml', (node,))


def error(source: str, keyvars: KeyVars) -> str:
    with pytest.raises(InstrumentError) as raised:
        instrument_source(code(source), keyvars, FILE)
    return str(raised.value)


def accepted(source: str, keyvars: KeyVars) -> None:
    assert instrument_source(code(source), keyvars, FILE).classes


# --- A: attribute paths --------------------------------------------------------------------

PATHS = '''
from rclpy.node import Node


class Pid:
    def __init__(self):
        self.accu_e = 0.0
        self.gains = Gains()


class Gains:
    kp = 1.0


class Controller(Node):
    def __init__(self):
        super().__init__('controller')
        self.pid = Pid()
'''


@pytest.mark.parametrize(
    ('vars', 'message'),
    [
        # The root is checked as a plain var; each missing root is named once.
        (('ekf.P', 'ekf.Q', 'pid'),
         'node.py:14:1: Controller never assigns self.ekf (vars: ekf.P, ekf.Q, pid)'),
        # The root holds a class of the module: it must assign the next segment.
        (('pid.accu',),
         'node.py:4:1: Pid never assigns self.accu, needed for pid.accu '
         '(self.pid = Pid() at line 17)'),
        # Recursively: Gains only has class attributes, and no ki.
        (('pid.gains.ki',),
         'node.py:10:1: Gains never assigns self.ki, needed for pid.gains.ki '
         '(self.gains = Gains() at line 7)'),
    ],
)
def test_path_errors(vars: tuple[str, ...], message: str) -> None:
    assert error(PATHS, spec('Controller', vars)) == message


@pytest.mark.parametrize(
    'vars',
    [
        ('pid', 'pid.gains.kp'),  # class attributes count
        ('pid.accu_e.real',),  # a float: beyond what the source shows
        ('pid.gains.kp.x.y',),
    ],
)
def test_paths_accepted(vars: tuple[str, ...]) -> None:
    accepted(PATHS, spec('Controller', vars))


@pytest.mark.parametrize(
    'pid',
    [
        # A base from elsewhere may add the attribute.
        'class Pid(control.PidBase):\n    def __init__(self):\n        self.kp = 1\n',
        # Attributes set by a computed name cannot be listed.
        'class Pid:\n    def __init__(self, **kw):\n        for k, v in kw.items():\n'
        '            setattr(self, k, v)\n',
        'class Pid:\n    def __init__(self, **kw):\n        self.__dict__.update(kw)\n',
        'class Pid:\n    def __getattr__(self, name):\n        return 0\n',
    ],
    ids=['library_base', 'setattr', 'dict', 'getattr'],
)
def test_path_into_an_open_class_is_accepted(pid: str) -> None:
    source = (
        'import control\nfrom rclpy.node import Node\n\n\n' + pid + '\n\n'
        'class C(Node):\n    def __init__(self):\n        self.pid = Pid()\n'
    )
    accepted(source, spec('C', ('pid.accu_e',)))


def test_path_checks_every_class_the_root_may_hold() -> None:
    source = '''
    from rclpy.node import Node


    class A:
        def __init__(self):
            self.x = 0


    class B:
        def __init__(self):
            self.y = 0


    class C(Node):
        def __init__(self, fast):
            self.f = A() if fast else None
            if fast:
                self.f = A()
            else:
                self.f = B()
    '''
    assert error(source, spec('C', ('f.x',))) == (
        'node.py:9:1: B never assigns self.x, needed for f.x (self.f = B() at line 20)'
    )


def test_path_in_nested_class() -> None:
    source = '''
    from rclpy.node import Node


    class Outer:
        class Pid:
            def __init__(self):
                self.kp = 1.0

        class Inner(Node):
            def __init__(self):
                self.pid = Outer.Pid()
    '''
    assert error(source, spec('Outer.Inner', ('pid.ki',))) == (
        'node.py:5:5: Outer.Pid never assigns self.ki, needed for pid.ki '
        '(self.pid = Outer.Pid() at line 11)'
    )


# --- B: module vars ------------------------------------------------------------------------

MODULE = '''
import numpy as np
import rclpy

counter = 0
squares = [n * n for n in range(3)]


class State:
    def __init__(self):
        self.pose = (0.0, 0.0)


state = State()


def main():
    global total
    total = 0
    local = 1
    node = rclpy.create_node('counter')
'''


@pytest.mark.parametrize(
    ('module_vars', 'message'),
    [
        (('counter', 'local'),
         "keyvars.yaml:5:30: module variable 'local' not found in node.py: it is never "
         "assigned at module level or after 'global local' in a function (globals there: "
         'counter, node, squares, state, total)'),
        # A comprehension's variable is its own; an import or a class is not a variable.
        (('n',),
         "keyvars.yaml:5:20: module variable 'n' not found in node.py: it is never assigned "
         "at module level or after 'global n' in a function (globals there: counter, node, "
         'squares, state, total)'),
        (('np',),
         "keyvars.yaml:5:20: module variable 'np' not found in node.py: it is never assigned "
         "at module level or after 'global np' in a function (globals there: counter, node, "
         'squares, state, total)'),
        (('State.pose',),
         "keyvars.yaml:5:20: module variable 'State' not found in node.py: it is never "
         "assigned at module level or after 'global State' in a function (globals there: "
         'counter, node, squares, state, total)'),
    ],
)
def test_module_var_not_found(module_vars: tuple[str, ...], message: str) -> None:
    with pytest.raises(ConfigError) as raised:
        instrument_source(code(MODULE.replace("    node = ", "    global node\n    node = ")),
                          spec(module_vars=module_vars), FILE)
    assert str(raised.value) == message


def test_module_var_path_into_a_class_of_the_module() -> None:
    accepted(MODULE, spec(module_vars=('counter', 'squares', 'total', 'state.pose')))
    assert error(MODULE, spec(module_vars=('state.heading',))) == (
        'node.py:8:1: State never assigns self.heading, needed for state.heading '
        '(state = State() at line 13)'
    )


def test_module_vars_with_a_class_are_checked_too() -> None:
    source = MODULE + '\n\nclass C(rclpy.node.Node):\n    def f(self):\n        self.x = 1\n'
    source = 'import rclpy.node\n' + code(source)
    with pytest.raises(ConfigError, match="module variable 'count' not found"):
        instrument_source(source, spec('C', ('x',), ('count',)), FILE)


# --- D: values that are not state ----------------------------------------------------------

NOT_STATE = [
    ('publisher', 'self.x = self.create_publisher(Int64, "out", 10)', 10, 9,
     'C.x holds a Publisher (self.create_publisher(...)), which is not state; list the data '
     'it publishes instead'),
    ('subscription', 'self.x = self.create_subscription(Int64, "in", self.cb, 10)', 10, 9,
     'C.x holds a Subscription (self.create_subscription(...)), which is not state; list the '
     'data its callback updates instead'),
    ('timer', 'self.x = self.create_timer(0.1, self.tick)', 10, 9,
     'C.x holds a Timer (self.create_timer(...)), which is not state; list the data its '
     'callback updates instead'),
    ('wall_timer', 'self.x = self.create_wall_timer(0.1, self.tick)', 10, 9,
     'C.x holds a Timer (self.create_wall_timer(...)), which is not state; list the data its '
     'callback updates instead'),
    ('client', 'self.x = self.create_client(Srv, "srv")', 10, 9,
     'C.x holds a Client (self.create_client(...)), which is not state; list the data its '
     'responses update instead'),
    ('service', 'self.x = self.create_service(Srv, "srv", self.cb)', 10, 9,
     'C.x holds a Service (self.create_service(...)), which is not state; list the data its '
     'handler updates instead'),
    ('guard_condition', 'self.x = self.create_guard_condition(self.cb)', 10, 9,
     'C.x holds a GuardCondition (self.create_guard_condition(...)), which is not state; the '
     'node creates it again when it starts'),
    ('rate', 'self.x = self.create_rate(10)', 10, 9,
     'C.x holds a Rate (self.create_rate(...)), which is not state; the node creates it '
     'again when it starts'),
    ('itself', 'self.x = self', 10, 9,
     'C.x holds the node itself (self), which is not state; list the data it keeps instead'),
    ('create_node', 'self.x = rclpy.create_node("helper")', 10, 9,
     'C.x holds a Node (rclpy.create_node(...)), which is not state; list the data the node '
     'keeps instead'),
    ('node_by_module_alias', 'self.x = rn.Node("helper")', 10, 9,
     'C.x holds a Node (rn.Node(...)), which is not state; list the data the node keeps '
     'instead'),
    ('node_of_the_module', 'self.x = C()', 10, 9,
     'C.x holds a Node (C()), which is not state; list the data the node keeps instead'),
    ('lock', 'self.x = threading.Lock()', 10, 9,
     'C.x holds a Lock (threading.Lock()), which is not state; list the data it guards '
     'instead'),
    ('lock_from_import', 'self.x = L()', 10, 9,
     'C.x holds an RLock (L()), which is not state; list the data it guards instead'),
    ('thread', 'self.x = threading.Thread(target=self.run)', 10, 9,
     'C.x holds a Thread (threading.Thread(...)), which is not state; list the data the '
     'thread updates instead'),
    ('event', 'self.x = threading.Event()', 10, 9,
     'C.x holds an Event (threading.Event()), which is not state; list the data it signals '
     'about instead'),
    ('condition', 'self.x = threading.Condition()', 10, 9,
     'C.x holds a Condition (threading.Condition()), which is not state; list the data it '
     'guards instead'),
    ('semaphore', 'self.x = threading.Semaphore(2)', 10, 9,
     'C.x holds a Semaphore (threading.Semaphore(...)), which is not state; list the data it '
     'guards instead'),
    ('multiprocessing', 'self.x = mp.Queue()', 10, 9,
     'C.x holds a multiprocessing.Queue (mp.Queue()), which is not state; list the data it '
     'carries instead'),
    ('file', 'self.x = open("log.txt", "a")', 10, 9,
     'C.x holds an open file (open(...)), which is not state; list the data read from or '
     'written to it instead'),
    ('socket', 'self.x = socket.socket()', 10, 9,
     'C.x holds a socket (socket.socket()), which is not state; list the data it carries '
     'instead'),
    ('process', 'self.x = subprocess.Popen(["ls"])', 10, 9,
     'C.x holds a process (subprocess.Popen(...)), which is not state; list the data '
     'exchanged with it instead'),
    # The assignment pointed at is the one that holds it, wherever it is.
    ('annotated', 'self.x: object = None\n        self.x: Publisher = self.create_publisher()',
     11, 9, 'C.x holds a Publisher (self.create_publisher()), which is not state; list the data '
     'it publishes instead'),
    ('unpacking', 'self.n, self.x = 0, self.create_timer(1.0, self.tick)', 10, 17,
     'C.x holds a Timer (self.create_timer(...)), which is not state; list the data its '
     'callback updates instead'),
    ('chained', 'self.y = self.x = threading.Lock()', 10, 18,
     'C.x holds a Lock (threading.Lock()), which is not state; list the data it guards '
     'instead'),
    ('setattr', 'setattr(self, "x", self.create_publisher(Int64, "out", 10))', 10, 9,
     'C.x holds a Publisher (self.create_publisher(...)), which is not state; list the data '
     'it publishes instead'),
    ('in_callback', 'def cb(msg):\n            self.x = open(msg.path)', 11, 13,
     'C.x holds an open file (open(...)), which is not state; list the data read from or '
     'written to it instead'),
    # State, but not what a checkpoint holds.
    ('defaultdict', 'from collections import defaultdict as dd\n        self.x = dd(list)', 11, 9,
     'C.x holds a defaultdict (dd(...)), which a checkpoint cannot hold: its default_factory '
     'is code; use a plain dict (dict.setdefault, dict.get)'),
    ('counter', 'import collections\n        self.x = collections.Counter()', 11, 9,
     'C.x holds a Counter (collections.Counter()), which a checkpoint cannot hold (a dict '
     'subclass); use a plain dict of counts (counts[k] = counts.get(k, 0) + 1)'),
]

HEADER = '''\
import multiprocessing as mp
import rclpy
import rclpy.node as rn
import socket, subprocess, threading
from threading import RLock as L


class C(rn.Node):
    def __init__(self):
        {body}
'''


@pytest.mark.parametrize(('body', 'line', 'col', 'message'), [c[1:] for c in NOT_STATE],
                         ids=[c[0] for c in NOT_STATE])
def test_not_state(body: str, line: int, col: int, message: str) -> None:
    source = HEADER.replace('{body}', body)
    assert error(source, spec('C', ('x',))) == f'node.py:{line}:{col}: {message}'


@pytest.mark.parametrize(
    'body',
    [
        'self.x = 0',
        'self.x = Publisher()',  # not visibly made by a node
        'self.x = factory.create_publisher()',  # resolved to an import: not a node method
        'self.x = create_publisher()',
        'self.x = self.make_lock()',
        'self.x = threading.local()',
        'with open("f") as self.x: pass',  # holds what __enter__ returns
        'self.x = [self.create_publisher(Int64, "out", 10)]',  # left to the runtime
        'self.x = 0\n        self.pub = self.create_publisher(Int64, "out", 10)',  # not listed
    ],
)
def test_state_accepted(body: str) -> None:
    source = 'import factory\n' + HEADER.replace('{body}', body)
    accepted(source, spec('C', ('x',)))


def test_not_state_in_a_base_class() -> None:
    source = '''
    import threading

    from rclpy.node import Node


    class Base(Node):
        def __init__(self):
            self.lock = threading.Lock()


    class Child(Base):
        pass
    '''
    assert error(source, spec('Child', ('lock',))) == (
        'node.py:8:9: Child.lock holds a Lock (threading.Lock()), which is not state; list '
        'the data it guards instead'
    )


def test_not_state_at_the_root_and_inside_a_path() -> None:
    source = '''
    import threading

    from rclpy.node import Node


    class Pid:
        def __init__(self, node):
            self.accu_e = 0.0
            self.lock = threading.Lock()
            self.node = node


    class C(Node):
        def __init__(self):
            self.pid = Pid(self)
            self.pub = self.create_publisher(int, 'out', 1)
    '''
    assert error(source, spec('C', ('pub.topic_name',))) == (
        'node.py:16:9: C.pub holds a Publisher (self.create_publisher(...)), which is not '
        'state; list the data it publishes instead'
    )
    assert error(source, spec('C', ('pid.lock',))) == (
        'node.py:9:9: Pid.lock holds a Lock (threading.Lock()), which is not state; list the '
        'data it guards instead'
    )
    # What the source does not show (a node passed in) is left to the runtime.
    accepted(source, spec('C', ('pid.accu_e', 'pid.node')))


def test_not_state_module_vars() -> None:
    source = '''
    import rclpy
    from rclpy.node import Node as N

    counter = 0
    node = rclpy.create_node('counter')
    pub = node.create_publisher(int, 'out', 1)


    def main():
        global other
        other = N('other')
    '''
    assert error(source, spec(module_vars=('counter', 'node'))) == (
        'node.py:5:1: module variable node holds a Node (rclpy.create_node(...)), which is not '
        'state; list the data the node keeps instead'
    )
    assert error(source, spec(module_vars=('pub',))) == (
        'node.py:6:1: module variable pub holds a Publisher (node.create_publisher(...)), which '
        'is not state; list the data it publishes instead'
    )
    assert error(source, spec(module_vars=('other',))) == (
        'node.py:11:5: module variable other holds a Node (N(...)), which is not state; list '
        'the data the node keeps instead'
    )


def test_errors_are_source_errors() -> None:
    with pytest.raises(SourceError):
        instrument_source(code(PATHS), spec('Controller', ('pid.accu',)), FILE)
