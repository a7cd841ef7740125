"""Before/after tests of the source rewrite, in the style of libcst's CodemodTest.

Expected outputs spell the decorator out in full; only the digest is a placeholder
(``<Class>``), filled in from the hash of the *before* text, which has no RORY additions.
"""
# Expected outputs are real source: the decorator line is as long as it is.
# ruff: noqa: E501

from __future__ import annotations

import hashlib
import textwrap
from dataclasses import dataclass, field

import libcst as cst
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_budget import examples

from rory_instrument.config import KeyVars, Mark, NodeSpec
from rory_instrument.errors import ConfigError, SourceError
from rory_instrument.manifest import manifest_digest
from rory_instrument.transform import (
    EnsureRuntimeImportTransformer,
    StripRoryTransformer,
    instrument_source,
)

FILE = 'node.py'


def code(text: str) -> str:
    return textwrap.dedent(text).lstrip('\n')


def keyvars(classes: dict[str, tuple[str, ...]], file: str = FILE) -> KeyVars:
    specs = tuple(
        NodeSpec(i, file, name, vars, marks={'': Mark(2 + 3 * i, 5), 'class': Mark(3 + 3 * i, 12)})
        for i, (name, vars) in enumerate(classes.items())
    )
    return KeyVars('keyvars.yaml', specs)


def instrument(source: str, classes: dict[str, tuple[str, ...]]) -> str:
    return instrument_source(source.encode(), keyvars(classes), FILE).code.decode()


def digest(source: str, class_name: str, vars: tuple[str, ...]) -> str:
    sha = hashlib.sha256(source.encode()).hexdigest()
    return manifest_digest(file=FILE, class_name=class_name, vars=vars, source_sha256=sha)


@dataclass
class Case:
    """``before`` instrumented with ``classes`` must give exactly ``after``."""

    id: str
    before: str
    after: str
    classes: dict[str, tuple[str, ...]]
    # The before text with RORY's additions removed, when it has any.
    stripped: str | None = field(default=None)

    def expected(self) -> str:
        text = code(self.after)
        basis = code(self.stripped if self.stripped is not None else self.before)
        for name, vars in self.classes.items():
            text = text.replace(f'<{name}>', digest(basis, name, vars))
        return text


CASES = [
    Case(
        'basic',
        '''
        import rclpy
        from rclpy.node import Node
        from std_msgs.msg import Int64


        class Integrator(Node):
            """Sums numbers."""

            def __init__(self):
                super().__init__('integrator')
                self.total = 0  # running sum
                self.count = 0
                self.history = []
        ''',
        '''
        import rclpy
        from rclpy.node import Node
        from std_msgs.msg import Int64
        import rory_runtime


        @rory_runtime.checkpointed(vars=("total", "count", "history"), manifest="<Integrator>")
        class Integrator(Node):
            """Sums numbers."""

            def __init__(self):
                super().__init__('integrator')
                self.total = 0  # running sum
                self.count = 0
                self.history = []
        ''',
        {'Integrator': ('total', 'count', 'history')},
    ),
    Case(
        'docstring_and_future',
        '''
        #!/usr/bin/env python3
        """A counting node."""

        from __future__ import annotations

        from rclpy.node import Node

        LIMIT = 10


        class Counter(Node):
            def __init__(self) -> None:
                super().__init__('counter')
                self.count: int = 0
        ''',
        '''
        #!/usr/bin/env python3
        """A counting node."""

        from __future__ import annotations

        from rclpy.node import Node
        import rory_runtime

        LIMIT = 10


        @rory_runtime.checkpointed(vars=("count",), manifest="<Counter>")
        class Counter(Node):
            def __init__(self) -> None:
                super().__init__('counter')
                self.count: int = 0
        ''',
        {'Counter': ('count',)},
    ),
    Case(
        # No import in the leading block: rclpy is imported inside a try statement.
        'no_leading_imports',
        '''
        """A counting node."""
        from __future__ import annotations

        try:
            from rclpy.node import Node
        except ImportError:  # pragma: no cover
            raise


        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        '''
        """A counting node."""
        from __future__ import annotations
        import rory_runtime

        try:
            from rclpy.node import Node
        except ImportError:  # pragma: no cover
            raise


        @rory_runtime.checkpointed(vars=("count",), manifest="<Counter>")
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        {'Counter': ('count',)},
    ),
    Case(
        'import_module_as',
        '''
        import rclpy.node as rn


        class Counter(rn.Node):
            def __init__(self):
                self.count = 0
        ''',
        '''
        import rclpy.node as rn
        import rory_runtime


        @rory_runtime.checkpointed(vars=("count",), manifest="<Counter>")
        class Counter(rn.Node):
            def __init__(self):
                self.count = 0
        ''',
        {'Counter': ('count',)},
    ),
    Case(
        'from_import_as',
        '''
        from rclpy.node import Node as N


        class Counter(N):
            def __init__(self):
                self.count = 0
        ''',
        '''
        from rclpy.node import Node as N
        import rory_runtime


        @rory_runtime.checkpointed(vars=("count",), manifest="<Counter>")
        class Counter(N):
            def __init__(self):
                self.count = 0
        ''',
        {'Counter': ('count',)},
    ),
    Case(
        'import_dotted_module',
        '''
        import rclpy
        import rclpy.node


        class Counter(rclpy.node.Node):
            def __init__(self):
                self.count = 0
        ''',
        '''
        import rclpy
        import rclpy.node
        import rory_runtime


        @rory_runtime.checkpointed(vars=("count",), manifest="<Counter>")
        class Counter(rclpy.node.Node):
            def __init__(self):
                self.count = 0
        ''',
        {'Counter': ('count',)},
    ),
    Case(
        'lifecycle_node',
        '''
        from rclpy.lifecycle import LifecycleNode


        class Counter(LifecycleNode):
            def on_configure(self, state):
                self.count = 0
        ''',
        '''
        from rclpy.lifecycle import LifecycleNode
        import rory_runtime


        @rory_runtime.checkpointed(vars=("count",), manifest="<Counter>")
        class Counter(LifecycleNode):
            def on_configure(self, state):
                self.count = 0
        ''',
        {'Counter': ('count',)},
    ),
    Case(
        # Child is a Node through Base, and assigns `count` only through Base.__init__.
        'derived_from_local_node',
        '''
        from rclpy.node import Node


        class Base(Node):
            def __init__(self, name):
                super().__init__(name)
                self.count = 0


        class Child(Base):
            def __init__(self):
                super().__init__('child')
                self.total = 0.0
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        class Base(Node):
            def __init__(self, name):
                super().__init__(name)
                self.count = 0


        @rory_runtime.checkpointed(vars=("total", "count"), manifest="<Child>")
        class Child(Base):
            def __init__(self):
                super().__init__('child')
                self.total = 0.0
        ''',
        {'Child': ('total', 'count')},
    ),
    Case(
        'nested_class',
        '''
        from rclpy.node import Node


        class Outer:
            """Holds the node."""

            class Inner(Node):
                def __init__(self):
                    self.count = 0
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        class Outer:
            """Holds the node."""

            @rory_runtime.checkpointed(vars=("count",), manifest="<Outer.Inner>")
            class Inner(Node):
                def __init__(self):
                    self.count = 0
        ''',
        {'Outer.Inner': ('count',)},
    ),
    Case(
        'existing_decorators',
        '''
        from dataclasses import dataclass

        from rclpy.node import Node

        from .registry import register


        # The registered node.
        @register('counter')
        # Plain decorator below.
        @final
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        '''
        from dataclasses import dataclass

        from rclpy.node import Node

        from .registry import register
        import rory_runtime


        # The registered node.
        @rory_runtime.checkpointed(vars=("count",), manifest="<Counter>")
        @register('counter')
        # Plain decorator below.
        @final
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        {'Counter': ('count',)},
    ),
    Case(
        'odd_formatting',
        '''
        # -*- coding: utf-8 -*-
        import os, sys  # two at once
        from rclpy.node import (
            Node,   # the base
        )
        x = 1; y = 2
        class   Weird (  Node ) :   # odd spacing
            def __init__( self ) :
                self.a , self.b = 1 , 2  # unpacking
                (self.c) = 3
                [self.d, *self.e] = [4, 5, 6]
                with open( os.devnull ) as self.f : pass
                for self.g in range( 3 ) : pass
                self.h += 1
                setattr(self, 'i', 9)
                def callback(msg):
                    self.j = msg
                self.k = [self.h for self.k in ()]



        # trailing comment
        ''',
        '''
        # -*- coding: utf-8 -*-
        import os, sys  # two at once
        from rclpy.node import (
            Node,   # the base
        )
        import rory_runtime
        x = 1; y = 2
        @rory_runtime.checkpointed(vars=("a", "b", "c", "d", "e", "f", "g", "h", "i", "j", "k"), manifest="<Weird>")
        class   Weird (  Node ) :   # odd spacing
            def __init__( self ) :
                self.a , self.b = 1 , 2  # unpacking
                (self.c) = 3
                [self.d, *self.e] = [4, 5, 6]
                with open( os.devnull ) as self.f : pass
                for self.g in range( 3 ) : pass
                self.h += 1
                setattr(self, 'i', 9)
                def callback(msg):
                    self.j = msg
                self.k = [self.h for self.k in ()]



        # trailing comment
        ''',
        {'Weird': tuple('abcdefghijk')},
    ),
    Case(
        'two_classes_one_listed',
        '''
        from rclpy.node import Node


        class Listed(Node):
            def __init__(self):
                self.count = 0


        class Unlisted(Node):
            def __init__(self):
                self.count = 0
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        @rory_runtime.checkpointed(vars=("count",), manifest="<Listed>")
        class Listed(Node):
            def __init__(self):
                self.count = 0


        class Unlisted(Node):
            def __init__(self):
                self.count = 0
        ''',
        {'Listed': ('count',)},
    ),
    Case(
        'two_classes_both_listed',
        '''
        from rclpy.node import Node


        class A(Node):
            def __init__(self):
                self.a = 0


        class B(Node):
            def __init__(self):
                self.b = 0
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        @rory_runtime.checkpointed(vars=("a",), manifest="<A>")
        class A(Node):
            def __init__(self):
                self.a = 0


        @rory_runtime.checkpointed(vars=("b",), manifest="<B>")
        class B(Node):
            def __init__(self):
                self.b = 0
        ''',
        {'A': ('a',), 'B': ('b',)},
    ),
    Case(
        # An aliased import of the runtime is reused rather than adding another.
        'runtime_imported_as_alias',
        '''
        import rory_runtime as rr
        from rclpy.node import Node


        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        '''
        import rory_runtime as rr
        from rclpy.node import Node


        @rr.checkpointed(vars=("count",), manifest="<Counter>")
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        {'Counter': ('count',)},
    ),
    Case(
        # A stale decorator (other vars, other digest) is updated in place, keeping its
        # position and its spelling; the import is already there.
        'stale_decorator_updated',
        '''
        from rclpy.node import Node
        from rory_runtime import checkpointed as cp


        @final
        @cp(
            vars=("old",),
            manifest="sha256:0000",
        )
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        '''
        from rclpy.node import Node
        from rory_runtime import checkpointed as cp


        @final
        @cp(
            vars=("count",),
            manifest="<Counter>",
        )
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        {'Counter': ('count',)},
        stripped='''
        from rclpy.node import Node
        from rory_runtime import checkpointed as cp


        @final
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
    ),
    Case(
        # Duplicates of RORY's decorator collapse into one.
        'duplicate_decorator_dropped',
        '''
        import rory_runtime
        from rclpy.node import Node


        @rory_runtime.checkpointed
        @rory_runtime.checkpointed(vars=("x",), manifest="sha256:1")
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        '''
        import rory_runtime
        from rclpy.node import Node


        @rory_runtime.checkpointed(vars=("count",), manifest="<Counter>")
        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
        {'Counter': ('count',)},
        stripped='''
        from rclpy.node import Node


        class Counter(Node):
            def __init__(self):
                self.count = 0
        ''',
    ),
    Case(
        # No __init__: the state is created by a callback and a lifecycle-style method.
        'no_init',
        '''
        from rclpy.node import Node


        class Counter(Node):
            def on_configure(self, state):
                self.count = 0

            def on_msg(self, msg):
                self.last = msg
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        @rory_runtime.checkpointed(vars=("count", "last"), manifest="<Counter>")
        class Counter(Node):
            def on_configure(self, state):
                self.count = 0

            def on_msg(self, msg):
                self.last = msg
        ''',
        {'Counter': ('count', 'last')},
    ),
    Case(
        # No body of its own at all: everything comes from the base's __init__.
        'no_init_inherited',
        '''
        from rclpy.node import Node


        class Base(Node):
            def __init__(self):
                super().__init__('base')
                self.count = 0


        class Child(Base):
            pass
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        class Base(Node):
            def __init__(self):
                super().__init__('base')
                self.count = 0


        @rory_runtime.checkpointed(vars=("count",), manifest="<Child>")
        class Child(Base):
            pass
        ''',
        {'Child': ('count',)},
    ),
    Case(
        # A var assigned only after an early return still counts.
        'init_early_return',
        '''
        from rclpy.node import Node


        class Counter(Node):
            def __init__(self, dry_run=False):
                super().__init__('counter')
                self.count = 0
                if dry_run:
                    return
                self.history = []
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        @rory_runtime.checkpointed(vars=("count", "history"), manifest="<Counter>")
        class Counter(Node):
            def __init__(self, dry_run=False):
                super().__init__('counter')
                self.count = 0
                if dry_run:
                    return
                self.history = []
        ''',
        {'Counter': ('count', 'history')},
    ),
    Case(
        # super().__init__ after the state, and inside a branch.
        'super_init_not_first',
        '''
        import rclpy.node as rn


        class Counter(rn.Node):
            def __init__(self, name=None):
                self.count = 0
                self.total = 0.0
                if name is None:
                    super().__init__('counter')
                else:
                    super().__init__(name)
        ''',
        '''
        import rclpy.node as rn
        import rory_runtime


        @rory_runtime.checkpointed(vars=("count", "total"), manifest="<Counter>")
        class Counter(rn.Node):
            def __init__(self, name=None):
                self.count = 0
                self.total = 0.0
                if name is None:
                    super().__init__('counter')
                else:
                    super().__init__(name)
        ''',
        {'Counter': ('count', 'total')},
    ),
]


def case_named(name: str) -> Case:
    return next(c for c in CASES if c.id == name)


@pytest.mark.parametrize('case', CASES, ids=lambda c: c.id)
def test_rewrite(case: Case) -> None:
    assert instrument(code(case.before), case.classes) == case.expected()


@pytest.mark.parametrize('case', CASES, ids=lambda c: c.id)
def test_idempotent(case: Case) -> None:
    once = instrument(code(case.before), case.classes)
    assert instrument(once, case.classes) == once


@pytest.mark.parametrize('case', CASES, ids=lambda c: c.id)
def test_strip_undoes_rewrite(case: Case) -> None:
    basis = code(case.stripped if case.stripped is not None else case.before)
    after = cst.MetadataWrapper(cst.parse_module(case.expected()))
    assert after.visit(StripRoryTransformer()).code == cst.MetadataWrapper(
        cst.parse_module(basis)
    ).visit(StripRoryTransformer()).code


def test_crlf_line_endings_are_kept() -> None:
    before = 'from rclpy.node import Node\r\n\r\nclass C(Node):\r\n    def f(self):\r\n' \
        '        self.x = 1\r\n'
    after = instrument(before, {'C': ('x',)})
    assert after == (
        'from rclpy.node import Node\r\nimport rory_runtime\r\n\r\n'
        f'@rory_runtime.checkpointed(vars=("x",), manifest="{digest(before, "C", ("x",))}")'
        '\r\nclass C(Node):\r\n    def f(self):\r\n        self.x = 1\r\n'
    )


def test_file_not_listed_is_returned_unchanged() -> None:
    source = b'this is not even Python (\n'
    result = instrument_source(source, keyvars({'C': ('x',)}, file='other.py'), FILE)
    assert result.code == source
    assert result.classes == ()


def test_result_lists_classes_with_digest() -> None:
    source = code(case_named('basic').before)
    result = instrument_source(source, keyvars(case_named('basic').classes), FILE)
    (done,) = result.classes
    assert done.spec.class_name == 'Integrator'
    assert done.source_sha256 == hashlib.sha256(source.encode()).hexdigest()
    assert done.manifest == digest(source, 'Integrator', ('total', 'count', 'history'))


def test_digest_depends_on_the_vars() -> None:
    source = code(case_named('basic').before)
    one = instrument(source, {'Integrator': ('total',)})
    two = instrument(source, {'Integrator': ('count',)})
    assert one != two


@pytest.mark.parametrize(
    ('before', 'after'),
    [
        ('X = 1\n', 'import rory_runtime\nX = 1\n'),
        ('"""Doc."""\n\nX = 1\n', '"""Doc."""\nimport rory_runtime\n\nX = 1\n'),
        ('#!/usr/bin/env python3\n# Header.\n\nX = 1\n',
         '#!/usr/bin/env python3\n# Header.\n\nimport rory_runtime\nX = 1\n'),
        ('import os\nimport rory_runtime\nX = 1\n', 'import os\nimport rory_runtime\nX = 1\n'),
        # Imported only after a definition: too late for a decorator, so added up front.
        ('import os\ndef f(): pass\nimport rory_runtime\n',
         'import os\nimport rory_runtime\ndef f(): pass\nimport rory_runtime\n'),
    ],
)
def test_ensure_runtime_import(before: str, after: str) -> None:
    assert cst.parse_module(before).visit(EnsureRuntimeImportTransformer()).code == after


def test_not_a_node_is_an_error() -> None:
    source = code(
        '''
        from rclpy.node import Node


        class Base:
            pass


        class Counter(Base, metaclass=type):
            def __init__(self):
                self.count = 0
        '''
    )
    with pytest.raises(SourceError) as raised:
        instrument_source(source, keyvars({'Counter': ('count',)}), FILE, display='src/node.py')
    assert str(raised.value) == (
        "src/node.py:8:1: class 'Counter' does not derive from rclpy.node.Node (bases: Base)"
    )


def test_shadowed_node_name_is_not_a_node() -> None:
    source = 'class Node:\n    pass\n\n\nclass C(Node):\n    def f(self):\n        self.x = 1\n'
    with pytest.raises(SourceError) as raised:
        instrument_source(source, keyvars({'C': ('x',)}), FILE)
    assert str(raised.value) == (
        "node.py:5:1: class 'C' does not derive from rclpy.node.Node (bases: Node)"
    )


def test_unimported_dotted_base_is_not_a_node() -> None:
    source = 'class C(rclpy.node.Node):\n    def f(self):\n        self.x = 1\n'
    with pytest.raises(SourceError, match=r'does not derive from rclpy\.node\.Node'):
        instrument_source(source, keyvars({'C': ('x',)}), FILE)


def test_class_not_found_points_at_keyvars() -> None:
    source = code(case_named('basic').before)
    with pytest.raises(ConfigError) as raised:
        instrument_source(source, keyvars({'Integrater': ('total',)}), FILE)
    assert str(raised.value) == (
        "keyvars.yaml:3:12: class 'Integrater' not found in node.py; classes there: Integrator"
    )


def test_nested_class_needs_its_dotted_name() -> None:
    source = code(case_named('nested_class').before)
    with pytest.raises(ConfigError) as raised:
        instrument_source(source, keyvars({'Inner': ('count',)}), FILE)
    assert str(raised.value).endswith(
        "class 'Inner' not found in node.py; classes there: Outer, Outer.Inner"
    )


@pytest.mark.parametrize(
    ('body', 'missing'),
    [
        ('self.total = 0', 'self.count'),
        ('self.count[0] = 1', 'self.count'),  # mutates, does not assign
        ('self.count: int', 'self.count'),  # declares, does not assign
        ('other.count = 1', 'self.count'),
        ('del self.count', 'self.count'),
    ],
)
def test_var_never_assigned(body: str, missing: str) -> None:
    source = f'from rclpy.node import Node\n\n\nclass C(Node):\n    def f(self, other):\n' \
        f'        {body}\n'
    with pytest.raises(SourceError) as raised:
        instrument_source(source, keyvars({'C': ('count',)}), FILE)
    assert str(raised.value) == f'node.py:4:1: C never assigns {missing} (vars: count)'


def test_every_missing_var_is_named() -> None:
    source = code(case_named('basic').before)
    with pytest.raises(SourceError) as raised:
        instrument_source(source, keyvars({'Integrator': ('totl', 'count', 'hist')}), FILE)
    assert str(raised.value) == (
        'node.py:6:1: Integrator never assigns self.totl, self.hist (vars: totl, count, hist)'
    )


def test_static_and_class_methods_do_not_count() -> None:
    source = code(
        '''
        from rclpy.node import Node


        class C(Node):
            @staticmethod
            def make(self):
                self.x = 1

            @classmethod
            def build(cls):
                cls.x = 1
        '''
    )
    with pytest.raises(SourceError, match=r'C never assigns self\.x'):
        instrument_source(source, keyvars({'C': ('x',)}), FILE)


def test_instance_parameter_need_not_be_called_self() -> None:
    source = 'from rclpy.node import Node\nclass C(Node):\n    def f(this):\n        this.x = 1\n'
    assert '@rory_runtime.checkpointed(vars=("x",)' in instrument(source, {'C': ('x',)})


def test_syntax_error_reports_python_position() -> None:
    with pytest.raises(SourceError) as raised:
        instrument_source('import os\ndef f(:\n    pass\n', keyvars({'C': ('x',)}), FILE)
    assert str(raised.value) == 'node.py:2:7: syntax error: invalid syntax'


@settings(max_examples=examples(40), deadline=None)
@given(
    vars=st.lists(st.sampled_from(['a', 'b', 'c', 'd']), min_size=1, unique=True),
    decorators=st.lists(st.sampled_from(['@final', '@register()', '# note']), max_size=3),
    blank=st.sampled_from(['', '\n', '\n\n']),
)
def test_idempotent_property(vars: list[str], decorators: list[str], blank: str) -> None:
    source = (
        '"""Doc."""\nfrom rclpy.node import Node\n' + blank + '\n'.join(decorators)
        + ('\n' if decorators else '') + 'class C(Node):\n    def f(self):\n'
        '        self.a = self.b = 1\n        self.c, self.d = 2, 3\n'
    )
    once = instrument(source, {'C': tuple(vars)})
    assert instrument(once, {'C': tuple(vars)}) == once
    assert once.count('checkpointed(') == 1
    assert once.count('import rory_runtime') == 1
