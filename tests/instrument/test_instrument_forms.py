"""Before/after tests of the forms beyond ``class`` + ``vars``: attribute paths, module vars,
per-node settings, freshness rules, the module call.

Expected outputs spell every addition out in full; only digests are placeholders: ``<Class>``
for a class entry, ``<module>`` for the entry without a class, filled in from the hash of the
*before* text (or of ``stripped`` when the before text already has RORY's additions).
"""
# Expected outputs are real source: the decorator and call lines are as long as they are.
# ruff: noqa: E501

from __future__ import annotations

import ast
import hashlib
import textwrap
from dataclasses import dataclass, field

import libcst as cst
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis_budget import examples

from rory_instrument.config import STALE_ACTIONS, FreshnessRule, KeyVars, Mark, NodeSpec
from rory_instrument.manifest import manifest_digest
from rory_instrument.transform import (
    CHECKPOINT_GLOBAL_PREFIX,
    StripRoryTransformer,
    freshness_argument,
    instrument_source,
)

FILE = 'node.py'


def code(text: str) -> str:
    return textwrap.dedent(text).lstrip('\n')


@dataclass(frozen=True)
class Entry:
    """One keyvars.yaml entry for ``FILE``."""

    class_name: str | None = None
    vars: tuple[str, ...] = ()
    module_vars: tuple[str, ...] = ()
    checkpoint_interval: float | None = None
    replay: str | None = None
    freshness: tuple[FreshnessRule, ...] = ()

    def spec(self, index: int) -> NodeSpec:
        return NodeSpec(
            index, FILE, self.class_name, self.vars, self.checkpoint_interval, self.replay,
            self.module_vars, self.freshness, marks={'': Mark(2 + 5 * index, 5)},
        )

    @property
    def placeholder(self) -> str:
        return f'<{self.class_name or "module"}>'


def rule(path: str, max_age: float, on_stale: str = 'reset', *, module: bool = False
         ) -> FreshnessRule:
    return FreshnessRule(path, max_age, on_stale, module)


def keyvars(entries: tuple[Entry, ...]) -> KeyVars:
    return KeyVars('keyvars.yaml', tuple(e.spec(i) for i, e in enumerate(entries)))


def instrument(source: str, entries: tuple[Entry, ...]) -> str:
    return instrument_source(source.encode(), keyvars(entries), FILE).code.decode()


def digest(source: str, entry: Entry) -> str:
    return manifest_digest(
        file=FILE, class_name=entry.class_name, vars=entry.vars,
        source_sha256=hashlib.sha256(source.encode()).hexdigest(),
        module_vars=entry.module_vars,
    )


@dataclass
class Case:
    """``before`` instrumented with ``entries`` must give exactly ``after``."""

    id: str
    before: str
    after: str
    entries: tuple[Entry, ...]
    # The before text with RORY's additions removed, when it has any.
    stripped: str | None = field(default=None)

    def expected(self) -> str:
        text = code(self.after)
        basis = code(self.stripped if self.stripped is not None else self.before)
        for entry in self.entries:
            text = text.replace(entry.placeholder, digest(basis, entry))
        return text


COUNTER = '''
"""A node written as functions."""
import rclpy
from std_msgs.msg import Int64

counter = 0
history = []


def on_msg(msg):
    global counter
    counter += msg.data
    history.append(msg.data)


def main():
    node = rclpy.create_node('counter')
    node.create_subscription(Int64, 'in', on_msg, 10)
    rclpy.spin(node)
'''

COUNTER_AFTER = '''
"""A node written as functions."""
import rclpy
from std_msgs.msg import Int64
import rory_runtime
rory_runtime.checkpoint_module(__name__, vars=("counter", "history"), manifest="<module>")

counter = 0
history = []


def on_msg(msg):
    global counter
    counter += msg.data
    history.append(msg.data)


def main():
    node = rclpy.create_node('counter')
    node.create_subscription(Int64, 'in', on_msg, 10)
    rclpy.spin(node)
'''

CASES = [
    Case(
        # `ekf` holds a class of the module, which assigns P; `pid` comes from a library,
        # so its accu_e is taken on trust.
        'attribute_paths',
        '''
        from rclpy.node import Node

        from control import Pid


        class Ekf:
            def __init__(self):
                self.x = [0.0, 0.0]
                self.P = [[1.0, 0.0], [0.0, 1.0]]


        class Tracker(Node):
            def __init__(self):
                super().__init__('tracker')
                self.total = 0
                self.ekf = Ekf()
                self.pid = Pid(kp=1.0)
        ''',
        '''
        from rclpy.node import Node

        from control import Pid
        import rory_runtime


        class Ekf:
            def __init__(self):
                self.x = [0.0, 0.0]
                self.P = [[1.0, 0.0], [0.0, 1.0]]


        @rory_runtime.checkpointed(vars=("total", "ekf.P", "pid.accu_e"), manifest="<Tracker>")
        class Tracker(Node):
            def __init__(self):
                super().__init__('tracker')
                self.total = 0
                self.ekf = Ekf()
                self.pid = Pid(kp=1.0)
        ''',
        (Entry('Tracker', ('total', 'ekf.P', 'pid.accu_e')),),
    ),
    Case(
        # Dataclass fields, properties and attributes of a base count; paths go deeper.
        'attribute_paths_deep',
        '''
        from dataclasses import dataclass, field

        from rclpy.node import Node


        @dataclass
        class Gains:
            kp: float = 1.0
            ki: float = 0.0


        class Filter:
            def __init__(self):
                self.state = 0.0


        class Pid(Filter):
            def __init__(self):
                super().__init__()
                self.gains = Gains()

            @property
            def error(self):
                return self.state


        class Controller(Node):
            def __init__(self):
                super().__init__('controller')
                self.pid = Pid()
        ''',
        '''
        from dataclasses import dataclass, field

        from rclpy.node import Node
        import rory_runtime


        @dataclass
        class Gains:
            kp: float = 1.0
            ki: float = 0.0


        class Filter:
            def __init__(self):
                self.state = 0.0


        class Pid(Filter):
            def __init__(self):
                super().__init__()
                self.gains = Gains()

            @property
            def error(self):
                return self.state


        @rory_runtime.checkpointed(vars=("pid.gains.ki", "pid.state", "pid.error"), manifest="<Controller>")
        class Controller(Node):
            def __init__(self):
                super().__init__('controller')
                self.pid = Pid()
        ''',
        (Entry('Controller', ('pid.gains.ki', 'pid.state', 'pid.error')),),
    ),
    Case(
        'nested_class_with_paths',
        '''
        from rclpy.node import Node


        class Outer:
            class Pid:
                def __init__(self):
                    self.accu_e = 0.0

            class Inner(Node):
                def __init__(self):
                    self.pid = Outer.Pid()
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        class Outer:
            class Pid:
                def __init__(self):
                    self.accu_e = 0.0

            @rory_runtime.checkpointed(vars=("pid.accu_e",), manifest="<Outer.Inner>")
            class Inner(Node):
                def __init__(self):
                    self.pid = Outer.Pid()
        ''',
        (Entry('Outer.Inner', ('pid.accu_e',)),),
    ),
    Case(
        'module_vars_alone',
        COUNTER,
        COUNTER_AFTER,
        (Entry(module_vars=('counter', 'history')),),
    ),
    Case(
        # A global assigned only through `global` in a function, with `:=` and in a
        # module-level `if` block; a path into a class of the module.
        'module_vars_forms',
        '''
        import rclpy


        class State:
            def __init__(self):
                self.pose = (0.0, 0.0)


        if True:
            state = State()


        def main():
            global ticks
            ticks = 0
            node = rclpy.create_node('ticker')
            if (last := None) is None:
                pass
        ''',
        '''
        import rclpy
        import rory_runtime
        rory_runtime.checkpoint_module(__name__, vars=("ticks", "state.pose"), manifest="<module>")


        class State:
            def __init__(self):
                self.pose = (0.0, 0.0)


        if True:
            state = State()


        def main():
            global ticks
            ticks = 0
            node = rclpy.create_node('ticker')
            if (last := None) is None:
                pass
        ''',
        (Entry(module_vars=('ticks', 'state.pose')),),
    ),
    Case(
        # No import at the top: the import and the call follow the docstring.
        'module_vars_no_imports',
        '''
        """Counts."""

        counter = 0
        ''',
        '''
        """Counts."""
        import rory_runtime
        rory_runtime.checkpoint_module(__name__, vars=("counter",), manifest="<module>")

        counter = 0
        ''',
        (Entry(module_vars=('counter',)),),
    ),
    Case(
        # An aliased import is reused; the call goes after the whole leading import block.
        'module_vars_runtime_alias',
        '''
        import rory_runtime as rr
        import rclpy

        counter = 0
        ''',
        '''
        import rory_runtime as rr
        import rclpy
        rr.checkpoint_module(__name__, vars=("counter",), manifest="<module>")

        counter = 0
        ''',
        (Entry(module_vars=('counter',)),),
    ),
    Case(
        'module_vars_with_settings',
        COUNTER,
        COUNTER_AFTER.replace(
            'manifest=', 'checkpoint_interval=0.5, replay="paced", manifest='
        ),
        (Entry(module_vars=('counter', 'history'), checkpoint_interval=0.5, replay='paced'),),
    ),
    Case(
        # A stale call is updated where it is, keeping its spelling and layout.
        'module_call_updated_in_place',
        '''
        import rclpy
        import rory_runtime as rr

        counter = 0
        rr.checkpoint_module(
            __name__,
            vars=("old",),
            manifest="sha256:0",
        )
        ''',
        '''
        import rclpy
        import rory_runtime as rr

        counter = 0
        rr.checkpoint_module(
            __name__,
            vars=("counter",),
            manifest="<module>",
        )
        ''',
        (Entry(module_vars=('counter',)),),
        stripped='''
        import rclpy
        import rory_runtime as rr

        counter = 0
        ''',
    ),
    Case(
        # Found by qualified name through a from-import; no `import rory_runtime` added;
        # a second copy is dropped; other arguments are replaced.
        'module_call_from_import',
        '''
        from rory_runtime import checkpoint_module as cm

        counter = 0
        cm(__name__, vars=("counter",), manifest="sha256:0")
        cm(__name__, vars=("x",), manifest="sha256:1")
        ''',
        '''
        from rory_runtime import checkpoint_module as cm

        counter = 0
        cm(__name__, vars=("counter",), replay="fast", manifest="<module>")
        ''',
        (Entry(module_vars=('counter',), replay='fast'),),
        stripped='''
        from rory_runtime import checkpoint_module as cm

        counter = 0
        ''',
    ),
    Case(
        # Class and module vars in one entry: one decorator, no module call.
        'module_vars_and_class',
        '''
        from rclpy.node import Node

        counter = 0


        class Integrator(Node):
            def __init__(self):
                super().__init__('integrator')
                self.total = 0
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime

        counter = 0


        @rory_runtime.checkpointed(vars=("total",), module_vars=("counter",), manifest="<Integrator>")
        class Integrator(Node):
            def __init__(self):
                super().__init__('integrator')
                self.total = 0
        ''',
        (Entry('Integrator', ('total',), ('counter',)),),
    ),
    Case(
        # A class with module vars only.
        'module_vars_and_class_without_vars',
        '''
        from rclpy.node import Node

        counter = 0


        class Integrator(Node):
            pass
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime

        counter = 0


        @rory_runtime.checkpointed(vars=(), module_vars=("counter",), checkpoint_interval=2.0, manifest="<Integrator>")
        class Integrator(Node):
            pass
        ''',
        (Entry('Integrator', (), ('counter',), checkpoint_interval=2.0),),
    ),
    Case(
        'settings_in_decorator',
        '''
        from rclpy.node import Node


        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime


        @rory_runtime.checkpointed(vars=("total",), checkpoint_interval=0.25, replay="fast", manifest="<Integrator>")
        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        (Entry('Integrator', ('total',), checkpoint_interval=0.25, replay='fast'),),
    ),
    Case(
        # Settings added to an aliased, hand-formatted decorator replace its arguments.
        'settings_added_to_existing_decorator',
        '''
        import rory_runtime as rr
        from rclpy.node import Node


        @rr.checkpointed(
            vars=("total",),
            manifest="sha256:0",
        )
        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        '''
        import rory_runtime as rr
        from rclpy.node import Node


        @rr.checkpointed(vars=("total",), replay="paced", manifest="<Integrator>")
        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        (Entry('Integrator', ('total',), replay='paced'),),
        stripped='''
        import rory_runtime as rr
        from rclpy.node import Node


        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
    ),
    Case(
        # A module entry and a class entry for the same file.
        'module_entry_and_class_entry',
        '''
        import rclpy
        from rclpy.node import Node

        counter = 0


        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        '''
        import rclpy
        from rclpy.node import Node
        import rory_runtime
        rory_runtime.checkpoint_module(__name__, vars=("counter",), manifest="<module>")

        counter = 0


        @rory_runtime.checkpointed(vars=("total",), manifest="<Integrator>")
        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        (Entry(module_vars=('counter',)), Entry('Integrator', ('total',))),
    ),
    Case(
        # Rules of vars and of module vars in one decorator, after the settings; a module
        # global's key has the checkpoint's `global:` prefix.
        'freshness_in_decorator',
        '''
        from rclpy.node import Node

        counter = 0


        class Tracker(Node):
            def __init__(self):
                super().__init__('tracker')
                self.total = 0
                self.history = []
                self.goal = None
        ''',
        '''
        from rclpy.node import Node
        import rory_runtime

        counter = 0


        @rory_runtime.checkpointed(vars=("total", "history", "goal"), module_vars=("counter",), replay="fast", freshness=(("history", 5.0, "reset"), ("goal", 30.0, "keep"), ("global:counter", 0.25, "refuse")), manifest="<Tracker>")
        class Tracker(Node):
            def __init__(self):
                super().__init__('tracker')
                self.total = 0
                self.history = []
                self.goal = None
        ''',
        (Entry('Tracker', ('total', 'history', 'goal'), ('counter',), replay='fast',
               freshness=(rule('history', 5.0), rule('goal', 30, 'keep'),
                          rule('counter', 0.25, 'refuse', module=True))),),
    ),
    Case(
        # One rule: a tuple of one tuple, with its comma.
        'freshness_in_module_call',
        COUNTER,
        COUNTER_AFTER.replace(
            'manifest=', 'checkpoint_interval=1.0, freshness=(("global:history", 2.5, "keep"),), manifest='
        ),
        (Entry(module_vars=('counter', 'history'), checkpoint_interval=1.0,
               freshness=(rule('history', 2.5, 'keep', module=True),)),),
    ),
    Case(
        # A rule added to a hand-formatted decorator: the arguments are rewritten.
        'freshness_added_to_existing_decorator',
        '''
        import rory_runtime as rr
        from rclpy.node import Node


        @rr.checkpointed(
            vars=("total",),
            manifest="sha256:0",
        )
        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        '''
        import rory_runtime as rr
        from rclpy.node import Node


        @rr.checkpointed(vars=("total",), freshness=(("total", 1e-05, "reset"),), manifest="<Integrator>")
        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        (Entry('Integrator', ('total',), freshness=(rule('total', 1e-5),)),),
        stripped='''
        import rory_runtime as rr
        from rclpy.node import Node


        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
    ),
    Case(
        # A changed rule is swapped in where the old one is, keeping the layout.
        'freshness_changed_in_place',
        '''
        import rclpy
        import rory_runtime

        counter = 0
        rory_runtime.checkpoint_module(
            __name__,
            vars=("counter",),
            freshness=(("global:counter", 5.0, "reset"),),
            manifest="sha256:0",
        )
        ''',
        '''
        import rclpy
        import rory_runtime

        counter = 0
        rory_runtime.checkpoint_module(
            __name__,
            vars=("counter",),
            freshness=(("global:counter", 60.0, "refuse"),),
            manifest="<module>",
        )
        ''',
        (Entry(module_vars=('counter',), freshness=(rule('counter', 60, 'refuse', module=True),)),),
        stripped='''
        import rclpy

        counter = 0
        ''',
    ),
    Case(
        # The rules removed from keyvars.yaml: the keyword goes too.
        'freshness_removed',
        '''
        import rory_runtime
        from rclpy.node import Node


        @rory_runtime.checkpointed(vars=("total",), freshness=(("total", 5.0, "reset"),), manifest="sha256:0")
        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        '''
        import rory_runtime
        from rclpy.node import Node


        @rory_runtime.checkpointed(vars=("total",), manifest="<Integrator>")
        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
        (Entry('Integrator', ('total',)),),
        stripped='''
        from rclpy.node import Node


        class Integrator(Node):
            def __init__(self):
                self.total = 0
        ''',
    ),
]


@pytest.mark.parametrize('case', CASES, ids=lambda c: c.id)
def test_rewrite(case: Case) -> None:
    assert instrument(code(case.before), case.entries) == case.expected()


@pytest.mark.parametrize('case', CASES, ids=lambda c: c.id)
def test_idempotent(case: Case) -> None:
    once = instrument(code(case.before), case.entries)
    assert instrument(once, case.entries) == once


@pytest.mark.parametrize('case', CASES, ids=lambda c: c.id)
def test_strip_undoes_rewrite(case: Case) -> None:
    basis = code(case.stripped if case.stripped is not None else case.before)

    def strip(text: str) -> str:
        return cst.MetadataWrapper(cst.parse_module(text)).visit(StripRoryTransformer()).code

    assert strip(case.expected()) == strip(basis)
    if case.stripped is None:
        assert strip(case.expected()) == basis


def test_settings_do_not_change_the_digest() -> None:
    plain = instrument_source(COUNTER, keyvars((Entry(module_vars=('counter',)),)), FILE)
    tuned = instrument_source(
        COUNTER, keyvars((Entry(module_vars=('counter',), checkpoint_interval=3.0),)), FILE
    )
    assert plain.classes[0].manifest == tuned.classes[0].manifest
    assert plain.code != tuned.code


def test_freshness_rules_do_not_change_the_digest() -> None:
    plain = instrument_source(COUNTER, keyvars((Entry(module_vars=('counter',)),)), FILE)
    ruled = instrument_source(
        COUNTER,
        keyvars((Entry(module_vars=('counter',), freshness=(rule('counter', 5.0, module=True),)),)),
        FILE,
    )
    assert plain.classes[0].manifest == ruled.classes[0].manifest
    assert plain.code != ruled.code
    # Without rules there is no keyword at all.
    assert b'freshness=' not in plain.code


def test_checkpoint_key_prefix_is_the_runtimes() -> None:
    from rory_runtime.node.state import GLOBAL_PREFIX

    assert CHECKPOINT_GLOBAL_PREFIX == GLOBAL_PREFIX


@settings(max_examples=examples(60), deadline=None)
@given(
    ages=st.lists(
        st.floats(min_value=5e-324, allow_nan=False, allow_infinity=False), min_size=1,
        max_size=3,
    ),
    actions=st.lists(st.sampled_from(STALE_ACTIONS), min_size=3, max_size=3),
    module=st.booleans(),
)
def test_freshness_keyword_reads_back(ages: list[float], actions: list[str],
                                      module: bool) -> None:
    names = ('a', 'b', 'c')[: len(ages)]
    rules = tuple(
        rule(n, age, a, module=module)
        for n, age, a in zip(names, ages, actions[: len(ages)], strict=True)
    )
    entry = (Entry(module_vars=names, freshness=rules) if module
             else Entry('C', names, freshness=rules))
    source = (
        'from rclpy.node import Node\na = b = c = 0\n\n\nclass C(Node):\n'
        '    def f(self):\n        self.a = self.b = self.c = 1\n'
    )
    once = instrument(source, (entry,))
    assert instrument(once, (entry,)) == once
    # The keyword holds exactly the runtime's value: the floats come back bit for bit.
    call = next(
        node for node in ast.walk(ast.parse(once))
        if isinstance(node, ast.Call) and any(k.arg == 'freshness' for k in node.keywords)
    )
    (keyword,) = (k for k in call.keywords if k.arg == 'freshness')
    assert ast.literal_eval(keyword.value) == freshness_argument(rules)


def test_module_vars_change_the_digest() -> None:
    source = code(
        '''
        from rclpy.node import Node

        counter = 0


        class C(Node):
            def f(self):
                self.x = 1
        '''
    )
    without = instrument_source(source, keyvars((Entry('C', ('x',)),)), FILE)
    with_ = instrument_source(source, keyvars((Entry('C', ('x',), ('counter',)),)), FILE)
    assert without.classes[0].manifest != with_.classes[0].manifest
    # Without module vars the digest is the one of the minimal schema.
    assert without.classes[0].manifest == manifest_digest(
        file=FILE, class_name='C', vars=('x',),
        source_sha256=hashlib.sha256(source.encode()).hexdigest(),
    )


def test_module_entry_is_reported() -> None:
    result = instrument_source(COUNTER, keyvars((Entry(module_vars=('counter',)),)), FILE)
    (done,) = result.classes
    assert done.spec.class_name is None
    assert done.spec.module_vars == ('counter',)
    assert done.source_sha256 == hashlib.sha256(COUNTER.encode()).hexdigest()


def test_crlf_module_call() -> None:
    before = 'import rclpy\r\n\r\ncounter = 0\r\n'
    entry = Entry(module_vars=('counter',))
    after = instrument(before, (entry,))
    assert after == (
        'import rclpy\r\nimport rory_runtime\r\n'
        f'rory_runtime.checkpoint_module(__name__, vars=("counter",), manifest="{digest(before, entry)}")'
        '\r\n\r\ncounter = 0\r\n'
    )


@settings(max_examples=examples(40), deadline=None)
@given(
    docstring=st.booleans(),
    imports=st.lists(
        st.sampled_from(['import rclpy', 'import rory_runtime', 'import rory_runtime as rr',
                         'from std_msgs.msg import Int64', '# a comment', '']),
        max_size=4,
    ),
    blank=st.sampled_from(['', '\n', '\n\n']),
    with_class=st.booleans(),
)
def test_module_call_property(docstring: bool, imports: list[str], blank: str,
                              with_class: bool) -> None:
    source = (
        ('"""Doc."""\n' if docstring else '') + ''.join(line + '\n' for line in imports)
        + blank + 'from rclpy.node import Node\ncounter = 0\n'
        + ('\n\nclass C(Node):\n    def f(self):\n        self.x = 1\n' if with_class else '')
    )
    entries = (Entry(module_vars=('counter',)),) + ((Entry('C', ('x',)),) if with_class else ())
    once = instrument(source, entries)
    assert instrument(once, entries) == once
    assert once.count('checkpoint_module(') == 1
    assert once.count('checkpointed(') == int(with_class)
    strip = cst.MetadataWrapper(cst.parse_module(once)).visit(StripRoryTransformer())
    original = cst.MetadataWrapper(cst.parse_module(source)).visit(StripRoryTransformer())
    assert strip.code == original.code
    # The call follows the line that binds the runtime, and nothing but imports precede it.
    lines = once.splitlines()
    call = next(i for i, line in enumerate(lines) if 'checkpoint_module(' in line)
    runtime = lines[call].split('.checkpoint_module')[0]
    binding = 'import rory_runtime' if runtime == 'rory_runtime' else f'import rory_runtime as {runtime}'
    assert binding in lines[:call]
    assert all(
        line.startswith(('import ', 'from ', '#', '"""')) or not line for line in lines[:call]
    )
