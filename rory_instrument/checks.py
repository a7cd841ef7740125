"""What a node module must show before it is instrumented, and the checks against keyvars.yaml.

Two read-only libcst passes collect the facts:

* ``ClassCollector``: every class, its bases, the ``self.<name>`` attributes its methods
  assign and the names its body defines, each assignment with its position and value.
* ``GlobalCollector``: the module globals assigned at module level or, after ``global
  name``, in a function.

``SpecChecker`` then checks each keyvars.yaml entry against them:

* the class exists, derives from ``rclpy.node.Node`` (through classes of the module too)
  and assigns the root of every path in ``vars`` (``ekf`` for ``ekf.P``);
* where a root is assigned an instance of a class of the module (``self.pid = Pid()``),
  that class assigns the next segment (``accu_e`` for ``pid.accu_e``), recursively; an
  attribute held by anything else may come from a library and is accepted;
* the root of every path in ``module_vars`` is a global of the module;
* no assignment to a listed variable (or root, or segment followed) visibly holds something
  that is not state: a ROS entity (``self.create_publisher(...)``), a node (``self``,
  ``rclpy.create_node(...)``), a lock or thread, a file, socket or process. What the source
  does not show is left to the runtime, which refuses it at the first checkpoint.

Calls are recognised by qualified name (``QualifiedNameProvider``), so ``from threading
import Lock as L`` is a lock too; ROS entity factories, being methods of a node, are
recognised by method name on whatever object they are called.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass

import libcst as cst
import libcst.matchers as m
from libcst.metadata import (
    MetadataWrapper,
    PositionProvider,
    QualifiedName,
    QualifiedNameProvider,
    QualifiedNameSource,
)

from rory_instrument.config import KeyVars, NodeSpec
from rory_instrument.errors import SourceError

# rclpy's Node and the rclpy classes derived from it that a node class may extend.
NODE_BASES = frozenset(
    {
        'rclpy.node.Node',
        'rclpy.lifecycle.Node',
        'rclpy.lifecycle.LifecycleNode',
        'rclpy.lifecycle.node.LifecycleNode',
    }
)
NODE_BASE = 'rclpy.node.Node'
# Bases known to add no instance attributes; a class whose other bases are all classes of
# the module is then fully visible.
PLAIN_BASES = frozenset(
    {'builtins.object', 'abc.ABC', 'typing.NamedTuple', 'typing.Generic', 'typing.Protocol'}
)

# Methods whose first parameter is not the instance.
NOT_INSTANCE_METHOD = m.Decorator(decorator=m.Name('staticmethod') | m.Name('classmethod'))
# `setattr(obj, 'name', value)` with a literal name.
SETATTR_CALL = m.Call(
    func=m.Name('setattr'), args=[m.Arg(keyword=None), m.Arg(value=m.SimpleString()), m.Arg()]
)
# `setattr(obj, name, value)` with a computed name: the attributes cannot be listed.
DYNAMIC_SETATTR_CALL = m.Call(
    func=m.Name('setattr'),
    args=[m.Arg(keyword=None), m.Arg(value=~m.SimpleString()), m.ZeroOrMore()],
)
# Methods that make any attribute name readable.
DYNAMIC_ATTRIBUTE_METHOD = m.FunctionDef(name=m.Name('__getattr__') | m.Name('__getattribute__'))


def _names_property(names: Collection[QualifiedName]) -> bool:
    return any(n.name in ('builtins.property', 'functools.cached_property') for n in names)


# `@property` or `@functools.cached_property`: the method reads as an attribute.
PROPERTY_DECORATOR = m.Decorator(
    decorator=m.MatchMetadataIfTrue(QualifiedNameProvider, _names_property)
)


@dataclass(frozen=True)
class NotState:
    """What a value visibly is when it is not state, as the refusal names it.

    Attributes:
        what: The value with its article: ``a Publisher``, ``the node itself``.
        hint: What to list instead.
        why: Why it cannot be a key variable.
    """

    what: str
    hint: str
    why: str = 'which is not state'


_NODE = NotState('a Node', 'list the data the node keeps instead')
_ITSELF = NotState('the node itself', 'list the data it keeps instead')
_SYNC = 'list the data it guards instead'
_THREAD = NotState('a Thread', 'list the data the thread updates instead')
_FILE = NotState('an open file', 'list the data read from or written to it instead')
_ACTION = 'list the data its callbacks update instead'
# Calls whose result is visibly not state, by the qualified name of the function called.
NOT_STATE_FUNCTIONS: Mapping[str, NotState] = {
    **{name: _NODE for name in (*NODE_BASES, 'rclpy.create_node')},
    'threading.Lock': NotState('a Lock', _SYNC),
    'threading.RLock': NotState('an RLock', _SYNC),
    'threading.Condition': NotState('a Condition', _SYNC),
    'threading.Semaphore': NotState('a Semaphore', _SYNC),
    'threading.BoundedSemaphore': NotState('a BoundedSemaphore', _SYNC),
    'threading.Event': NotState('an Event', 'list the data it signals about instead'),
    'threading.Barrier': NotState('a Barrier', _SYNC),
    'threading.Thread': _THREAD,
    'threading.Timer': _THREAD,
    'builtins.open': _FILE,
    'io.open': _FILE,
    'os.fdopen': _FILE,
    'socket.socket': NotState('a socket', 'list the data it carries instead'),
    'subprocess.Popen': NotState('a process', 'list the data exchanged with it instead'),
    'rclpy.action.ActionClient': NotState('an ActionClient', _ACTION),
    'rclpy.action.ActionServer': NotState('an ActionServer', _ACTION),
    # State, but not what a checkpoint holds (codec.py refuses them at the first checkpoint).
    'collections.defaultdict': NotState(
        'a defaultdict', 'use a plain dict (dict.setdefault, dict.get)',
        'which a checkpoint cannot hold: its default_factory is code'),
    'collections.Counter': NotState(
        'a Counter', 'use a plain dict of counts (counts[k] = counts.get(k, 0) + 1)',
        'which a checkpoint cannot hold (a dict subclass)'),
}
# Modules whose every object belongs to the running process.
NOT_STATE_MODULES: Mapping[str, str] = {
    'multiprocessing': 'list the data it carries instead',
}
# A node's entity factories, by method name on any receiver (`self.`, `node.`).
NOT_STATE_METHODS: Mapping[str, NotState] = {
    'create_publisher': NotState('a Publisher', 'list the data it publishes instead'),
    'create_subscription': NotState(
        'a Subscription', 'list the data its callback updates instead'
    ),
    'create_timer': NotState('a Timer', 'list the data its callback updates instead'),
    'create_wall_timer': NotState('a Timer', 'list the data its callback updates instead'),
    'create_client': NotState('a Client', 'list the data its responses update instead'),
    'create_service': NotState('a Service', 'list the data its handler updates instead'),
    'create_guard_condition': NotState(
        'a GuardCondition', 'the node creates it again when it starts'
    ),
    'create_rate': NotState('a Rate', 'the node creates it again when it starts'),
}


@dataclass(frozen=True)
class Assignment:
    """One assignment to a checked attribute or global.

    Attributes:
        target: The target as messages show it: ``self.pid``, ``counter``.
        line: 1-based line of the target.
        col: 1-based column of the target.
        value: The value as messages show it when it is a call (``Pid(...)``,
            ``threading.Lock()``) or the instance itself (``self``); None otherwise.
        callee: Qualified names of the function called, when the value is a call.
        resolved: Whether ``callee`` names an import or a builtin (not just a local).
        method: The method name when the value is a call ``<expr>.<method>(...)``.
        is_instance: The value is the instance the attribute belongs to (``self``).
    """

    target: str
    line: int
    col: int
    value: str | None = None
    callee: frozenset[str] = frozenset()
    resolved: bool = False
    method: str | None = None
    is_instance: bool = False


# The raw finding of an assignment visitor: name, target node and, when shown, value node.
_Found = tuple[str, cst.CSTNode, cst.BaseExpression | None]


def _paired_values(
    target: cst.Tuple | cst.List, value: cst.BaseExpression | None
) -> list[cst.BaseExpression | None]:
    """Returns the value each element of an unpacking target receives, where it is visible."""
    targets = target.elements
    if isinstance(value, cst.Tuple | cst.List) and len(value.elements) == len(targets):
        elements = (*targets, *value.elements)
        if not any(isinstance(e, cst.StarredElement) for e in elements):
            return [e.value for e in value.elements]
    return [None] * len(targets)


class _AssignmentVisitor(cst.CSTVisitor):
    """Collects assignments to the targets ``tracked`` names; subclasses say which.

    Assignment forms: ``=``, annotated ``=``, augmented, tuple/list unpacking (starred
    too), ``with ... as`` and ``for ... in``. The value is kept where the source shows what
    the target receives: ``=`` and annotated ``=``, element by element for unpacking a
    tuple or list display of the same length.
    """

    def __init__(self) -> None:
        super().__init__()
        self.found: list[_Found] = []

    def tracked(self, target: cst.BaseExpression) -> str | None:
        """Returns the name a target assigns, if it is one this visitor collects."""
        raise NotImplementedError

    def _target(self, target: cst.BaseExpression, value: cst.BaseExpression | None) -> None:
        name = self.tracked(target)
        if name is not None:
            self.found.append((name, target, value))
        elif isinstance(target, cst.Tuple | cst.List):
            for element, part in zip(
                target.elements, _paired_values(target, value), strict=True
            ):
                self._target(element.value, part)

    def visit_Assign(self, node: cst.Assign) -> None:
        for target in node.targets:
            self._target(target.target, node.value)

    def visit_AnnAssign(self, node: cst.AnnAssign) -> None:
        # `x: int` alone declares without assigning; only count it with a value.
        if node.value is not None:
            self._target(node.target, node.value)

    def visit_AugAssign(self, node: cst.AugAssign) -> None:
        self._target(node.target, None)

    def visit_For(self, node: cst.For) -> None:
        self._target(node.target, None)

    def visit_WithItem(self, node: cst.WithItem) -> None:
        # The target gets what `__enter__` returns, which the source does not show.
        if node.asname is not None:
            self._target(node.asname.name, None)


class SelfAssignments(_AssignmentVisitor):
    """Collects the ``<self>.<name>`` attributes a method body assigns.

    Besides the forms of every assignment visitor: comprehension targets and ``setattr(self,
    'x', ...)``. Nested functions are searched because node callbacks are often closures
    over ``self``; nested classes are not, since there ``self`` is another object.

    Args:
        self_name: The method's first parameter name, usually ``self``.
    """

    def __init__(self, self_name: str) -> None:
        super().__init__()
        self.self_name = self_name
        # Attributes are also set in ways that cannot be listed (`setattr(self, k, v)`).
        self.dynamic = False

    @property
    def assigned(self) -> set[str]:
        """The attribute names assigned."""
        return {name for name, _target, _value in self.found}

    def tracked(self, target: cst.BaseExpression) -> str | None:
        if isinstance(target, cst.Attribute) and m.matches(target.value, m.Name(self.self_name)):
            return target.attr.value
        return None

    def visit_CompFor(self, node: cst.CompFor) -> None:
        self._target(node.target, None)

    def visit_Call(self, node: cst.Call) -> None:
        if not node.args or not m.matches(node.args[0].value, m.Name(self.self_name)):
            return
        if m.matches(node, SETATTR_CALL):
            name = node.args[1].value
            assert isinstance(name, cst.SimpleString)
            self.found.append((str(name.evaluated_value), node, node.args[2].value))
        elif m.matches(node, DYNAMIC_SETATTR_CALL):
            self.dynamic = True

    def visit_Attribute(self, node: cst.Attribute) -> None:
        if m.matches(node, m.Attribute(value=m.Name(self.self_name), attr=m.Name('__dict__'))):
            self.dynamic = True

    def visit_ClassDef(self, node: cst.ClassDef) -> bool:
        return False

    def visit_FunctionDef(self, node: cst.FunctionDef) -> bool:
        # A nested function that takes its own `self` is not about this instance.
        params = node.params
        every = (*params.posonly_params, *params.params, *params.kwonly_params)
        return all(p.name.value != self.self_name for p in every)


class ClassBodyNames(_AssignmentVisitor):
    """Collects the names a class body assigns or declares (``x = 0``, ``x: float``).

    Dataclass and NamedTuple fields are declared this way. Visited statement by statement;
    methods and nested classes are skipped.
    """

    def tracked(self, target: cst.BaseExpression) -> str | None:
        return target.value if isinstance(target, cst.Name) else None

    def visit_AnnAssign(self, node: cst.AnnAssign) -> None:
        self._target(node.target, node.value)

    def visit_FunctionDef(self, node: cst.FunctionDef) -> bool:
        return False

    def visit_ClassDef(self, node: cst.ClassDef) -> bool:
        return False

    def visit_Lambda(self, node: cst.Lambda) -> bool:
        return False


class GlobalDeclarations(cst.CSTVisitor):
    """Collects the names a function body declares ``global``, not looking into nested scopes."""

    def __init__(self) -> None:
        super().__init__()
        self.names: set[str] = set()

    def visit_Global(self, node: cst.Global) -> None:
        self.names.update(item.name.value for item in node.names)

    def visit_FunctionDef(self, node: cst.FunctionDef) -> bool:
        return False

    def visit_ClassDef(self, node: cst.ClassDef) -> bool:
        return False

    def visit_Lambda(self, node: cst.Lambda) -> bool:
        return False


class GlobalAssignments(_AssignmentVisitor):
    """Collects assignments to module globals.

    A name is a global where it is assigned at module level (inside ``if``, ``try``,
    ``with``... too) or in a function that declares it ``global``. Comprehension variables
    are local to the comprehension; ``:=`` binds in the enclosing scope.
    """

    def __init__(self) -> None:
        super().__init__()
        # The names declared global in each enclosing function; empty: module level.
        self.scopes: list[frozenset[str]] = []

    def tracked(self, target: cst.BaseExpression) -> str | None:
        if isinstance(target, cst.Name) and (not self.scopes or target.value in self.scopes[-1]):
            return target.value
        return None

    def visit_NamedExpr(self, node: cst.NamedExpr) -> None:
        self._target(node.target, node.value)

    def visit_FunctionDef(self, node: cst.FunctionDef) -> None:
        declarations = GlobalDeclarations()
        node.body.visit(declarations)
        self.scopes.append(frozenset(declarations.names))

    def leave_FunctionDef(self, original_node: cst.FunctionDef) -> None:
        self.scopes.pop()

    def visit_ClassDef(self, node: cst.ClassDef) -> None:
        self.scopes.append(frozenset())

    def leave_ClassDef(self, original_node: cst.ClassDef) -> None:
        self.scopes.pop()

    def visit_Lambda(self, node: cst.Lambda) -> None:
        self.scopes.append(frozenset())

    def leave_Lambda(self, original_node: cst.Lambda) -> None:
        self.scopes.pop()


def describe(
    resolver: cst.MetadataDependent,
    module: cst.Module,
    found: _Found,
    owner: str | None,
) -> tuple[str, Assignment]:
    """Turns a visitor's finding into an ``Assignment``, resolving position and callee.

    Args:
        resolver: A visitor of the module with Position and QualifiedName metadata.
        module: The module, to render the callee for messages.
        found: The name, target node and value node.
        owner: The instance parameter name (``self``) for attributes, None for globals.

    Returns:
        The name assigned and the assignment.
    """
    name, target, value = found
    start = resolver.get_metadata(PositionProvider, target).start
    shown = name if owner is None else f'{owner}.{name}'
    assignment = Assignment(shown, start.line, start.column + 1)
    if owner is not None and value is not None and m.matches(value, m.Name(owner)):
        return name, Assignment(shown, start.line, start.column + 1, owner, is_instance=True)
    if isinstance(value, cst.Call):
        qualified = resolver.get_metadata(QualifiedNameProvider, value.func, set())
        method = value.func.attr.value if isinstance(value.func, cst.Attribute) else None
        assignment = Assignment(
            shown,
            start.line,
            start.column + 1,
            value=module.code_for_node(value.func) + ('(...)' if value.args else '()'),
            callee=frozenset(q.name for q in qualified),
            resolved=any(q.source is not QualifiedNameSource.LOCAL for q in qualified),
            method=method,
        )
    return name, assignment


def _group(pairs: Iterator[tuple[str, Assignment]]) -> dict[str, tuple[Assignment, ...]]:
    grouped: dict[str, list[Assignment]] = {}
    for name, assignment in pairs:
        grouped.setdefault(name, []).append(assignment)
    return {name: tuple(items) for name, items in grouped.items()}


@dataclass(frozen=True)
class ClassFacts:
    """What the checks need to know about one class of the module.

    Attributes:
        name: Dotted qualified name, as Python's ``__qualname__`` (``Outer.Inner``).
        line: 1-based line of the ``class`` keyword.
        col: 1-based column of the ``class`` keyword.
        bases: Each positional base: its source text and its possible qualified names.
        assigned: Attribute names assigned as ``self.<name>`` in the class's own methods.
        assignments: Those assignments, by attribute name, in source order.
        body_names: Names the class body assigns or declares (fields, class attributes,
            properties), by name, with their assignments.
        dynamic: The class sets or reads attributes in ways that cannot be listed
            (``setattr(self, k, v)``, ``self.__dict__``, ``__getattr__``).
    """

    name: str
    line: int
    col: int
    bases: tuple[tuple[str, frozenset[str]], ...]
    assigned: frozenset[str]
    assignments: Mapping[str, tuple[Assignment, ...]]
    body_names: Mapping[str, tuple[Assignment, ...]]
    dynamic: bool = False


def class_qualname(resolver: cst.MetadataDependent, node: cst.ClassDef) -> str | None:
    """Returns the dotted qualified name of a class, or None if libcst cannot tell."""
    names = resolver.get_metadata(QualifiedNameProvider, node.name, set())
    local = sorted(n.name for n in names)
    return local[0] if local else None


def _instance_methods(node: cst.ClassDef) -> Iterator[tuple[cst.FunctionDef, str]]:
    """Yields each method defined directly in a class body with its instance parameter."""
    if not isinstance(node.body, cst.IndentedBlock):
        return
    for statement in node.body.body:
        if not isinstance(statement, cst.FunctionDef):
            continue
        if any(m.matches(d, NOT_INSTANCE_METHOD) for d in statement.decorators):
            continue
        params = (*statement.params.posonly_params, *statement.params.params)
        if params:
            yield statement, params[0].name.value


class ClassCollector(cst.CSTVisitor):
    """Collects ``ClassFacts`` for every class of a module, in source order.

    Args:
        module: The module being visited, to render bases and values for messages.
    """

    METADATA_DEPENDENCIES = (QualifiedNameProvider, PositionProvider)

    def __init__(self, module: cst.Module) -> None:
        super().__init__()
        self.module = module
        self.classes: dict[str, ClassFacts] = {}

    def visit_ClassDef(self, node: cst.ClassDef) -> None:
        name = class_qualname(self, node)
        if name is None or name in self.classes:
            return
        start = self.get_metadata(PositionProvider, node).start
        bases = tuple(
            (
                self.module.code_for_node(arg.value),
                frozenset(
                    q.name for q in self.get_metadata(QualifiedNameProvider, arg.value, set())
                ),
            )
            for arg in node.bases
            if arg.keyword is None
        )
        found: list[tuple[str, Assignment]] = []
        dynamic = False
        for method, self_name in _instance_methods(node):
            collector = SelfAssignments(self_name)
            method.body.visit(collector)
            found.extend(describe(self, self.module, f, self_name) for f in collector.found)
            dynamic |= collector.dynamic
        body_names, body_dynamic = self._body_names(node)
        self.classes[name] = ClassFacts(
            name,
            start.line,
            start.column + 1,
            bases,
            frozenset(n for n, _a in found),
            _group(iter(found)),
            body_names,
            dynamic or body_dynamic,
        )

    def _body_names(self, node: cst.ClassDef) -> tuple[dict[str, tuple[Assignment, ...]], bool]:
        """Returns the names a class body defines and whether it reads attributes dynamically."""
        if not isinstance(node.body, cst.IndentedBlock):
            return {}, False
        found: list[tuple[str, Assignment]] = []
        dynamic = False
        collector = ClassBodyNames()
        for statement in node.body.body:
            if isinstance(statement, cst.FunctionDef):
                dynamic |= m.matches(statement, DYNAMIC_ATTRIBUTE_METHOD)
                if any(
                    m.matches(d, PROPERTY_DECORATOR, metadata_resolver=self)
                    for d in statement.decorators
                ):
                    start = self.get_metadata(PositionProvider, statement.name).start
                    found.append((statement.name.value, Assignment(
                        statement.name.value, start.line, start.column + 1
                    )))
            elif not isinstance(statement, cst.ClassDef):
                statement.visit(collector)
        found.extend(describe(self, self.module, f, None) for f in collector.found)
        return _group(iter(found)), dynamic


class GlobalCollector(cst.CSTVisitor):
    """Collects the module globals a module assigns, with each assignment.

    Args:
        module: The module being visited, to render values for messages.
    """

    METADATA_DEPENDENCIES = (QualifiedNameProvider, PositionProvider)

    def __init__(self, module: cst.Module) -> None:
        super().__init__()
        self.module = module
        self.globals: dict[str, tuple[Assignment, ...]] = {}

    def visit_Module(self, node: cst.Module) -> bool:
        collector = GlobalAssignments()
        node.visit(collector)
        self.globals = _group(describe(self, self.module, f, None) for f in collector.found)
        return False


@dataclass(frozen=True)
class ModuleFacts:
    """What the checks know about one module.

    Attributes:
        file: Its path relative to SRC, POSIX separators (resolves relative imports).
        display: How messages name it.
        classes: Its classes, by dotted name, in source order.
        globals: Its module globals, by name, with their assignments.
    """

    file: str
    display: str
    classes: Mapping[str, ClassFacts]
    globals: Mapping[str, tuple[Assignment, ...]]


# Finds a base class named by an import (`.base.BaseNode`, `pkg.base.BaseNode`) in another
# module of SRC: the module and the class's dotted name there, or None.
BaseResolver = Callable[[ModuleFacts, str], 'tuple[ModuleFacts, str] | None']


def collect_module(wrapper: MetadataWrapper, file: str, display: str) -> ModuleFacts:
    """Runs the collectors over a module.

    Args:
        wrapper: The module, wrapped for metadata.
        file: Its path relative to SRC.
        display: How messages name it.

    Returns:
        Its classes and globals.
    """
    classes = ClassCollector(wrapper.module)
    wrapper.visit(classes)
    globals_ = GlobalCollector(wrapper.module)
    wrapper.visit(globals_)
    return ModuleFacts(file, display, classes.classes, globals_.globals)


def lineage(
    module: ModuleFacts, name: str, resolve: BaseResolver | None = None
) -> list[tuple[ModuleFacts, ClassFacts]]:
    """Returns a class and, transitively, its bases defined in the module or, with
    ``resolve``, in other modules of SRC; each with the module it is in."""
    seen: dict[tuple[str, str], tuple[ModuleFacts, ClassFacts]] = {}
    pending = [(module, name)]
    while pending:
        current, class_name = pending.pop()
        key = (current.file, class_name)
        if key in seen or class_name not in current.classes:
            continue
        seen[key] = (current, current.classes[class_name])
        for _text, names in current.classes[class_name].bases:
            for base in sorted(names):
                if base in current.classes:
                    pending.append((current, base))
                elif resolve is not None and base not in NODE_BASES:
                    found = resolve(current, base)
                    if found is not None:
                        pending.append(found)
    return list(seen.values())


def is_node(module: ModuleFacts, name: str, resolve: BaseResolver | None = None) -> bool:
    """Returns whether a class derives from an rclpy Node class."""
    return any(
        names & NODE_BASES
        for _module, c in lineage(module, name, resolve)
        for _text, names in c.bases
    )


def fully_visible(module: ModuleFacts, name: str) -> bool:
    """Returns whether every attribute of a class's instances shows in its module.

    False when a base comes from elsewhere (it may add attributes) or when attributes are
    set or read dynamically.
    """
    for _module, facts in lineage(module, name):
        if facts.dynamic:
            return False
        for _text, names in facts.bases:
            if not (names & module.classes.keys() or (names and names <= PLAIN_BASES)):
                return False
    return True


def not_state(
    assignment: Assignment, module: ModuleFacts, resolve: BaseResolver | None = None
) -> NotState | None:
    """Returns what an assigned value visibly is if that is not state, else None.

    Args:
        assignment: The assignment.
        module: The module it is in.
        resolve: Finds classes of other modules, to recognise their node classes.
    """
    if assignment.is_instance:
        return _ITSELF
    for name in sorted(assignment.callee):
        if name in NOT_STATE_FUNCTIONS:
            return NOT_STATE_FUNCTIONS[name]
        root = name.partition('.')[0]
        if root in NOT_STATE_MODULES:
            return NotState(f'a {name}', NOT_STATE_MODULES[root])
        if name in module.classes and is_node(module, name, resolve):
            return _NODE
        if resolve is not None and assignment.resolved and root != 'builtins':
            found = resolve(module, name)
            if found is not None and is_node(*found, resolve):
                return _NODE
    if not assignment.resolved and assignment.method is not None:
        return NOT_STATE_METHODS.get(assignment.method)
    return None


# An assignment with the module it is in.
_Placed = tuple[ModuleFacts, Assignment]


class SpecChecker:
    """Checks keyvars.yaml entries against the facts of one module.

    Args:
        keyvars: The configuration, to locate errors in it.
        module: The module's facts.
        resolve: Finds base classes in other modules of SRC; None to look in the module
            only.
    """

    def __init__(
        self, keyvars: KeyVars, module: ModuleFacts, resolve: BaseResolver | None = None
    ) -> None:
        self.keyvars = keyvars
        self.module = module
        self.resolve = resolve

    def check(self, spec: NodeSpec) -> None:
        """Raises the first problem with ``spec``.

        Raises:
            ConfigError: The class, or the root of a module var, is not in the file.
            SourceError: Any other problem, located in the source.
        """
        if spec.class_name is not None:
            self.check_class(spec, spec.class_name)
        globals_ = self.module.globals
        for index, path in enumerate(spec.module_vars):
            root = path.split('.')[0]
            if root not in globals_:
                there = ', '.join(sorted(globals_)) or 'none'
                raise self.keyvars.error(
                    spec, f'module_vars[{index}]',
                    f'module variable {root!r} not found in {spec.file}: it is never assigned '
                    f"at module level or after 'global {root}' in a function (globals there: "
                    f'{there})',
                )
            placed = [(self.module, a) for a in globals_[root]]
            self.check_path(path, path.split('.'), None, placed)

    def check_class(self, spec: NodeSpec, class_name: str) -> None:
        """Checks the class of an entry and the roots of its ``vars``."""
        module = self.module
        facts = module.classes.get(class_name)
        if facts is None:
            there = ', '.join(module.classes) or 'none'
            raise self.keyvars.error(
                spec, 'class',
                f'class {class_name!r} not found in {spec.file}; classes there: {there}',
            )
        fail = functools.partial(SourceError, module.display, facts.line, facts.col)
        if not is_node(module, class_name, self.resolve):
            bases = ', '.join(text for text, _names in facts.bases) or 'none'
            raise fail(f'class {class_name!r} does not derive from {NODE_BASE} (bases: {bases})')
        assignments: dict[str, list[_Placed]] = {}
        for where, c in lineage(module, class_name, self.resolve):
            for name, items in c.assignments.items():
                assignments.setdefault(name, []).extend((where, a) for a in items)
        roots = [v.split('.')[0] for v in spec.vars]
        missing = list(dict.fromkeys(r for r in roots if r not in assignments))
        if missing:
            raise fail(
                f'{class_name} never assigns {", ".join("self." + v for v in missing)} '
                f'(vars: {", ".join(spec.vars)})'
            )
        for path, root in zip(spec.vars, roots, strict=True):
            self.check_path(path, path.split('.'), class_name, assignments[root])

    def check_path(
        self,
        path: str,
        segments: Sequence[str],
        owner: str | None,
        assignments: Sequence[_Placed],
    ) -> None:
        """Checks what ``segments[0]`` holds, then the rest of the path in classes of the module.

        Args:
            path: The whole path as listed, for messages.
            segments: The part of the path still to check; ``segments[0]`` is assigned by
                ``assignments``.
            owner: The class ``segments[0]`` is an attribute of, or None for a global.
            assignments: Every assignment of ``segments[0]``, each with its module.
        """
        name = segments[0]
        holder = f'module variable {name}' if owner is None else f'{owner}.{name}'
        for module, assignment in assignments:
            held = not_state(assignment, module, self.resolve)
            if held is not None:
                raise SourceError(
                    module.display, assignment.line, assignment.col,
                    f'{holder} holds {held.what} ({assignment.value}), {held.why}; '
                    f'{held.hint}',
                )
        if len(segments) == 1:
            return
        attribute = segments[1]
        for module, assignment in assignments:
            for class_name in sorted(assignment.callee & module.classes.keys()):
                if not fully_visible(module, class_name):
                    continue
                provided: dict[str, list[_Placed]] = {}
                for _where, c in lineage(module, class_name):
                    for attr, items in (*c.assignments.items(), *c.body_names.items()):
                        provided.setdefault(attr, []).extend((module, a) for a in items)
                if attribute not in provided:
                    facts = module.classes[class_name]
                    raise SourceError(
                        module.display, facts.line, facts.col,
                        f'{class_name} never assigns self.{attribute}, needed for {path} '
                        f'({assignment.target} = {assignment.value} at line {assignment.line})',
                    )
                self.check_path(path, segments[1:], class_name, provided[attribute])
