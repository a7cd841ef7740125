"""Rewriting one node module: add ``@rory_runtime.checkpointed(...)`` and ``import rory_runtime``.

The rewrite is a handful of small libcst passes, one per concern:

* ``ClassCollector`` reads what the checks need: every class, its bases, and the
  ``self.<name>`` attributes its methods assign.
* ``StripRoryTransformer`` removes RORY's own additions, so the source hash in the manifest
  is the same for a file and for its instrumented output.
* ``CheckpointDecoratorTransformer`` adds the decorator, or updates the arguments of one
  that is already there, which is what makes instrumenting twice a no-op.
* ``EnsureRuntimeImportTransformer`` adds ``import rory_runtime`` after the leading imports.

Names are matched by qualified name (``QualifiedNameProvider``), so ``from rclpy.node
import Node as N`` and ``import rclpy.node as rn`` are recognised like the plain spelling.
"""

from __future__ import annotations

import ast
import hashlib
from collections.abc import Collection, Iterator, Mapping, Sequence
from dataclasses import dataclass

import libcst as cst
import libcst.matchers as m
from libcst.metadata import (
    MetadataWrapper,
    PositionProvider,
    QualifiedName,
    QualifiedNameProvider,
)

from rory_instrument.config import KeyVars, NodeSpec
from rory_instrument.errors import SourceError
from rory_instrument.manifest import manifest_digest

RUNTIME_MODULE = 'rory_runtime'
CHECKPOINTED = f'{RUNTIME_MODULE}.checkpointed'
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


def _names_checkpointed(names: Collection[QualifiedName]) -> bool:
    return any(name.name == CHECKPOINTED for name in names)


# `rory_runtime.checkpointed`, however rory_runtime or checkpointed was imported.
IS_CHECKPOINTED = m.MatchMetadataIfTrue(QualifiedNameProvider, _names_checkpointed)
# RORY's decorator, called (`@rory_runtime.checkpointed(...)`) or, if someone wrote it by
# hand, bare (`@rory_runtime.checkpointed`).
RORY_DECORATOR = m.Decorator(decorator=m.Call(func=IS_CHECKPOINTED) | IS_CHECKPOINTED)
# Exactly the line RORY adds: `import rory_runtime`.
RUNTIME_IMPORT_LINE = m.SimpleStatementLine(
    body=[m.Import(names=[m.ImportAlias(name=m.Name(RUNTIME_MODULE), asname=None)])]
)
# Any import of the module itself, possibly aliased: `import os, rory_runtime as rr`.
RUNTIME_IMPORT = m.Import(
    names=[m.ZeroOrMore(), m.ImportAlias(name=m.Name(RUNTIME_MODULE)), m.ZeroOrMore()]
)
# A line of the leading import block (`from __future__` included).
IMPORT_LINE = m.SimpleStatementLine(body=[m.AtLeastN(m.Import() | m.ImportFrom(), n=1)])
DOCSTRING_LINE = m.SimpleStatementLine(
    body=[m.Expr(value=m.SimpleString() | m.ConcatenatedString())]
)
# Methods whose first parameter is not the instance.
NOT_INSTANCE_METHOD = m.Decorator(decorator=m.Name('staticmethod') | m.Name('classmethod'))
# `setattr(obj, 'name', value)` with a literal name.
SETATTR_CALL = m.Call(
    func=m.Name('setattr'), args=[m.Arg(keyword=None), m.Arg(value=m.SimpleString()), m.Arg()]
)
# Top-level definitions; RORY's import must come before the first one to be usable there.
DEFINITION = m.ClassDef() | m.FunctionDef()


@dataclass(frozen=True)
class ClassFacts:
    """What the checks need to know about one class of the module.

    Attributes:
        name: Dotted qualified name, as Python's ``__qualname__`` (``Outer.Inner``).
        line: 1-based line of the ``class`` keyword.
        col: 1-based column of the ``class`` keyword.
        bases: Each positional base: its source text and its possible qualified names.
        assigned: Attribute names assigned as ``self.<name>`` in the class's own methods.
    """

    name: str
    line: int
    col: int
    bases: tuple[tuple[str, frozenset[str]], ...]
    assigned: frozenset[str]


@dataclass(frozen=True)
class InstrumentedClass:
    """One class that was decorated.

    Attributes:
        spec: Its keyvars.yaml entry.
        source_sha256: SHA-256 of the module's source with RORY's additions removed.
        manifest: The ``sha256:...`` digest written into the decorator.
    """

    spec: NodeSpec
    source_sha256: str
    manifest: str


@dataclass(frozen=True)
class InstrumentedModule:
    """The result of instrumenting one source file.

    Attributes:
        code: The new source, in the file's own encoding.
        classes: The classes decorated, in keyvars.yaml order.
    """

    code: bytes
    classes: tuple[InstrumentedClass, ...]


def class_qualname(resolver: cst.MetadataDependent, node: cst.ClassDef) -> str | None:
    """Returns the dotted qualified name of a class, or None if libcst cannot tell."""
    names = resolver.get_metadata(QualifiedNameProvider, node.name, set())
    local = sorted(n.name for n in names)
    return local[0] if local else None


class SelfAssignments(cst.CSTVisitor):
    """Collects the ``<self>.<name>`` attributes a method body assigns.

    Assignment forms: ``=``, annotated ``=``, augmented, tuple/list unpacking (starred
    too), ``with ... as``, ``for ... in`` (comprehensions too), and ``setattr(self, 'x',
    ...)``. Nested functions are searched because node callbacks are often closures over
    ``self``; nested classes are not, since there ``self`` is another object.

    Args:
        self_name: The method's first parameter name, usually ``self``.
    """

    def __init__(self, self_name: str) -> None:
        super().__init__()
        self.self_name = self_name
        self.assigned: set[str] = set()

    def _target(self, target: cst.BaseExpression) -> None:
        if isinstance(target, cst.Attribute):
            if m.matches(target.value, m.Name(self.self_name)):
                self.assigned.add(target.attr.value)
        elif isinstance(target, cst.Tuple | cst.List):
            for element in target.elements:
                self._target(element.value)

    def visit_Assign(self, node: cst.Assign) -> None:
        for target in node.targets:
            self._target(target.target)

    def visit_AnnAssign(self, node: cst.AnnAssign) -> None:
        # `self.x: int` alone declares without assigning; only count it with a value.
        if node.value is not None:
            self._target(node.target)

    def visit_AugAssign(self, node: cst.AugAssign) -> None:
        self._target(node.target)

    def visit_For(self, node: cst.For) -> None:
        self._target(node.target)

    def visit_CompFor(self, node: cst.CompFor) -> None:
        self._target(node.target)

    def visit_WithItem(self, node: cst.WithItem) -> None:
        if node.asname is not None:
            self._target(node.asname.name)

    def visit_Call(self, node: cst.Call) -> None:
        if m.matches(node, SETATTR_CALL) and m.matches(
            node.args[0].value, m.Name(self.self_name)
        ):
            name = node.args[1].value
            assert isinstance(name, cst.SimpleString)
            self.assigned.add(str(name.evaluated_value))

    def visit_ClassDef(self, node: cst.ClassDef) -> bool:
        return False

    def visit_FunctionDef(self, node: cst.FunctionDef) -> bool:
        # A nested function that takes its own `self` is not about this instance.
        params = node.params
        every = (*params.posonly_params, *params.params, *params.kwonly_params)
        return all(p.name.value != self.self_name for p in every)


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
        module: The module being visited, to render base expressions for messages.
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
        assigned: set[str] = set()
        for method, self_name in _instance_methods(node):
            collector = SelfAssignments(self_name)
            method.body.visit(collector)
            assigned |= collector.assigned
        self.classes[name] = ClassFacts(
            name, start.line, start.column + 1, bases, frozenset(assigned)
        )


class StripRoryTransformer(cst.CSTTransformer):
    """Removes RORY's decorators and top-level ``import rory_runtime`` lines.

    Used only to compute the source hash: a file and its instrumented output strip to the
    same text, so both get the same manifest.
    """

    METADATA_DEPENDENCIES = (QualifiedNameProvider,)

    def leave_Decorator(
        self, original_node: cst.Decorator, updated_node: cst.Decorator
    ) -> cst.Decorator | cst.RemovalSentinel:
        if m.matches(original_node, RORY_DECORATOR, metadata_resolver=self):
            return cst.RemoveFromParent()
        return updated_node

    def leave_Module(self, original_node: cst.Module, updated_node: cst.Module) -> cst.Module:
        body = [s for s in updated_node.body if not m.matches(s, RUNTIME_IMPORT_LINE)]
        return updated_node.with_changes(body=body)


def checkpointed_call(runtime: str, vars: Sequence[str], manifest: str) -> cst.Call:
    """Builds ``<runtime>.checkpointed(vars=(...), manifest="...")``.

    Args:
        runtime: The name rory_runtime is bound to in the module.
        vars: Attribute names; identifiers, so they need no escaping.
        manifest: The ``sha256:...`` digest.

    Returns:
        The call expression.
    """
    names = ', '.join(f'"{v}"' for v in vars) + (',' if len(vars) == 1 else '')
    call = cst.parse_expression(f'{runtime}.checkpointed(vars=({names}), manifest="{manifest}")')
    assert isinstance(call, cst.Call)
    return call


def _with_new_arguments(decorator: cst.Decorator, new: cst.Call) -> cst.Decorator:
    """Gives an existing RORY decorator the arguments of ``new``, keeping its spelling."""
    old = decorator.decorator
    if not isinstance(old, cst.Call):
        return decorator.with_changes(decorator=new.with_changes(func=old))
    values = {arg.keyword.value: arg.value for arg in new.args if arg.keyword is not None}
    keywords = [arg.keyword.value if arg.keyword is not None else '' for arg in old.args]
    if sorted(keywords) == sorted(values):
        # Same keywords: swap the values only, so hand formatting of the call survives.
        args = [
            arg.with_changes(value=values[kw])
            for arg, kw in zip(old.args, keywords, strict=True)
        ]
        return decorator.with_changes(decorator=old.with_changes(args=args))
    return decorator.with_changes(decorator=old.with_changes(args=new.args))


class CheckpointDecoratorTransformer(cst.CSTTransformer):
    """Puts ``@<runtime>.checkpointed(vars=..., manifest=...)`` on the named classes.

    A class without the decorator gets it as its outermost decorator; a class that has it
    (found by qualified name) gets its arguments replaced, and any second copy dropped.

    Args:
        calls: The decorator call for each class, by dotted class name (spelled with the
            name rory_runtime is bound to in the module).
    """

    METADATA_DEPENDENCIES = (QualifiedNameProvider,)

    def __init__(self, calls: Mapping[str, cst.Call]) -> None:
        super().__init__()
        self.calls = calls
        self.added = False

    def leave_ClassDef(
        self, original_node: cst.ClassDef, updated_node: cst.ClassDef
    ) -> cst.ClassDef:
        name = class_qualname(self, original_node)
        if name is None or name not in self.calls:
            return updated_node
        call = self.calls[name]
        decorators: list[cst.Decorator] = []
        found = False
        # The decorators themselves are not transformed, so original and updated align.
        pairs = zip(original_node.decorators, updated_node.decorators, strict=True)
        for original, updated in pairs:
            if not m.matches(original, RORY_DECORATOR, metadata_resolver=self):
                decorators.append(updated)
            elif not found:
                decorators.append(_with_new_arguments(updated, call))
                found = True
        if not found:
            decorators.insert(0, cst.Decorator(decorator=call))
            self.added = True
        return updated_node.with_changes(decorators=decorators)


def runtime_binding(module: cst.Module) -> str | None:
    """Returns the name ``import rory_runtime [as name]`` binds before the first definition.

    Only top-level imports ahead of the first class or function count: a later one would
    not be bound yet when a decorator runs.
    """
    for statement in module.body:
        if m.matches(statement, DEFINITION):
            break
        if not isinstance(statement, cst.SimpleStatementLine):
            continue
        for small in statement.body:
            if not m.matches(small, RUNTIME_IMPORT):
                continue
            assert isinstance(small, cst.Import)
            for alias in small.names:
                if m.matches(alias.name, m.Name(RUNTIME_MODULE)):
                    return alias.evaluated_alias or RUNTIME_MODULE
    return None


def import_insertion_index(body: Sequence[cst.BaseStatement]) -> int:
    """Returns where ``import rory_runtime`` goes: after the leading docstring and imports."""
    index = 1 if body and m.matches(body[0], DOCSTRING_LINE) else 0
    while index < len(body) and m.matches(body[index], IMPORT_LINE):
        index += 1
    return index


class EnsureRuntimeImportTransformer(cst.CSTTransformer):
    """Adds ``import rory_runtime`` after the module's leading imports unless it is bound."""

    def leave_Module(self, original_node: cst.Module, updated_node: cst.Module) -> cst.Module:
        if runtime_binding(updated_node) == RUNTIME_MODULE:
            return updated_node
        body = list(updated_node.body)
        body.insert(import_insertion_index(body), cst.parse_statement(f'import {RUNTIME_MODULE}\n'))
        return updated_node.with_changes(body=body)


def parse_source(source: bytes, display: str) -> cst.Module:
    """Parses a module, turning a syntax error into a SourceError at its position.

    Python's own parser runs first: its messages are the ones users know, and it rejects
    code libcst's more permissive grammar accepts.

    Args:
        source: The file's bytes (an encoding declaration is honoured).
        display: How to name the file in messages.

    Returns:
        The parsed module.

    Raises:
        SourceError: The file is not valid Python.
    """
    try:
        ast.parse(source, filename=display)
    except SyntaxError as e:
        raise SourceError(display, e.lineno or 0, e.offset or 0, f'syntax error: {e.msg}') from e
    except ValueError as e:  # null bytes, on some Python versions
        raise SourceError(display, 0, 0, f'syntax error: {e}') from e
    try:
        return cst.parse_module(source)
    except cst.ParserSyntaxError as e:
        message = f'syntax error: {e.message}'
        raise SourceError(display, e.raw_line, e.raw_column + 1, message) from e


def source_sha256(wrapper: MetadataWrapper) -> str:
    """Returns the SHA-256 of a module's source with RORY's additions removed."""
    return hashlib.sha256(wrapper.visit(StripRoryTransformer()).bytes).hexdigest()


def _lineage(classes: Mapping[str, ClassFacts], name: str) -> list[ClassFacts]:
    """Returns a class and, transitively, its bases defined in the same module."""
    seen: dict[str, ClassFacts] = {}
    pending = [name]
    while pending:
        current = pending.pop()
        if current in seen or current not in classes:
            continue
        seen[current] = classes[current]
        for _text, names in classes[current].bases:
            pending.extend(sorted(names))
    return list(seen.values())


def _check(
    keyvars: KeyVars, spec: NodeSpec, classes: Mapping[str, ClassFacts], display: str
) -> None:
    """Raises the first problem with ``spec`` against the module's classes."""
    facts = classes.get(spec.class_name)
    if facts is None:
        there = ', '.join(classes) or 'none'
        raise keyvars.error(
            spec, 'class',
            f'class {spec.class_name!r} not found in {spec.file}; classes there: {there}',
        )
    lineage = _lineage(classes, spec.class_name)
    if not any(names & NODE_BASES for c in lineage for _text, names in c.bases):
        bases = ', '.join(text for text, _names in facts.bases) or 'none'
        raise SourceError(
            display, facts.line, facts.col,
            f'class {spec.class_name!r} does not derive from {NODE_BASE} (bases: {bases})',
        )
    assigned = frozenset().union(*(c.assigned for c in lineage))
    missing = [v for v in spec.vars if v not in assigned]
    if missing:
        raise SourceError(
            display, facts.line, facts.col,
            f'{spec.class_name} never assigns {", ".join("self." + v for v in missing)} '
            f'(vars: {", ".join(spec.vars)})',
        )


def instrument_source(
    source: bytes | str,
    keyvars: KeyVars,
    file: str,
    *,
    display: str | None = None,
    specs: Sequence[NodeSpec] | None = None,
) -> InstrumentedModule:
    """Instruments the classes that keyvars.yaml lists for one file.

    Args:
        source: The file's content.
        keyvars: The configuration; names keyvars.yaml in messages.
        file: The file's path relative to SRC, POSIX separators, as in the manifest.
        display: How to name the file in messages; defaults to ``file``.
        specs: The entries to apply; defaults to those of ``keyvars`` whose ``file`` is
            ``file`` (the tree step passes them itself once it has resolved paths).

    Returns:
        The new source and what was decorated. With no entries for ``file`` the source is
        returned unchanged.

    Raises:
        SourceError: The file is not valid Python, or a listed class is not a Node or
            does not assign one of its vars.
        ConfigError: A listed class is not in the file.
    """
    raw = source.encode('utf-8') if isinstance(source, str) else source
    if specs is None:
        specs = [s for s in keyvars.nodes if s.file == file]
    shown = file if display is None else display
    if not specs:
        return InstrumentedModule(raw, ())
    module = parse_source(raw, shown)
    wrapper = MetadataWrapper(module)
    collector = ClassCollector(wrapper.module)
    wrapper.visit(collector)
    for spec in specs:
        _check(keyvars, spec, collector.classes, shown)

    digest = source_sha256(wrapper)
    binding = runtime_binding(wrapper.module)
    runtime = binding or RUNTIME_MODULE
    done: list[InstrumentedClass] = []
    calls: dict[str, cst.Call] = {}
    for spec in specs:
        manifest = manifest_digest(
            file=file, class_name=spec.class_name, vars=spec.vars, source_sha256=digest
        )
        done.append(InstrumentedClass(spec, digest, manifest))
        calls[spec.class_name] = checkpointed_call(runtime, spec.vars, manifest)

    decorate = CheckpointDecoratorTransformer(calls)
    result = wrapper.visit(decorate)
    if decorate.added and binding is None:
        result = result.visit(EnsureRuntimeImportTransformer())
    return InstrumentedModule(result.bytes, tuple(done))
