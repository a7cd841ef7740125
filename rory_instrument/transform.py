"""Rewriting one node module: ``import rory_runtime``, the decorator and the module call.

For a node class the rewrite adds one decorator, and for a node written as functions, whose
state is in module globals, one call right after ``import rory_runtime``::

    import rory_runtime
    rory_runtime.checkpoint_module(__name__, vars=("counter",), manifest="sha256:...")


    @rory_runtime.checkpointed(vars=("total", "ekf.P"), manifest="sha256:...")
    class Integrator(Node):

Either takes ``checkpoint_interval=1.0, replay="fast"`` before the digest when keyvars.yaml
sets them, then ``freshness=(("history", 5.0, "reset"), ("global:counter", 30.0, "refuse"))``
when entries have freshness rules: one ``(checkpoint key, max_age, on_stale)`` per rule, the
key of a module global prefixed with ``global:`` as in the checkpoint. A class whose entry
also lists module globals gets ``module_vars=("counter",)`` after its ``vars`` instead of a
module call. The checks run first (``rory_instrument.checks``); the rewrite is then a handful
of small libcst passes, one per concern:

* ``StripRoryTransformer`` removes RORY's own additions, so the source hash in the manifest
  is the same for a file and for its instrumented output.
* ``CheckpointModuleTransformer`` adds the module call, or updates the arguments of one
  that is already there.
* ``CheckpointDecoratorTransformer`` adds the decorator, or updates the arguments of one
  that is already there. Updating in place is what makes instrumenting twice a no-op.
* ``EnsureRuntimeImportTransformer`` adds ``import rory_runtime`` after the leading imports.

Names are matched by qualified name (``QualifiedNameProvider``), so ``from rclpy.node
import Node as N``, ``import rclpy.node as rn`` and ``import rory_runtime as rr`` are
recognised like the plain spelling.
"""

from __future__ import annotations

import ast
import hashlib
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass

import libcst as cst
import libcst.matchers as m
from libcst.metadata import MetadataWrapper, QualifiedName, QualifiedNameProvider

from rory_instrument.checks import (
    NODE_BASE,
    NODE_BASES,
    BaseResolver,
    SpecChecker,
    class_qualname,
    collect_module,
)
from rory_instrument.clocks import wall_clock_warnings
from rory_instrument.config import FreshnessRule, KeyVars, NodeSpec
from rory_instrument.entities import check_entities
from rory_instrument.errors import SourceError
from rory_instrument.manifest import manifest_digest

__all__ = [
    'NODE_BASE',
    'NODE_BASES',
    'CheckpointDecoratorTransformer',
    'CheckpointModuleTransformer',
    'EnsureRuntimeImportTransformer',
    'InstrumentedClass',
    'InstrumentedModule',
    'StripRoryTransformer',
    'checkpoint_key',
    'checkpoint_module_call',
    'checkpointed_call',
    'freshness_argument',
    'instrument_source',
    'parse_source',
    'source_sha256',
]

RUNTIME_MODULE = 'rory_runtime'
CHECKPOINTED = f'{RUNTIME_MODULE}.checkpointed'
CHECKPOINT_MODULE = f'{RUNTIME_MODULE}.checkpoint_module'
# A checkpoint stores a module global under this prefix and its path; the same as
# rory_runtime.node.state.GLOBAL_PREFIX, spelled out so that instrumenting needs no runtime.
CHECKPOINT_GLOBAL_PREFIX = 'global:'
# The rules of an entry as the runtime takes them: (checkpoint key, max_age in seconds,
# on_stale) each.
FreshnessArgument = tuple[tuple[str, float, str], ...]


def _names(qualified: str) -> Callable[[Collection[QualifiedName]], bool]:
    def named(names: Collection[QualifiedName]) -> bool:
        return any(name.name == qualified for name in names)

    return named


# `rory_runtime.checkpointed`, however rory_runtime or checkpointed was imported.
IS_CHECKPOINTED = m.MatchMetadataIfTrue(QualifiedNameProvider, _names(CHECKPOINTED))
# `rory_runtime.checkpoint_module`, however it was imported.
IS_CHECKPOINT_MODULE = m.MatchMetadataIfTrue(QualifiedNameProvider, _names(CHECKPOINT_MODULE))
# RORY's decorator, called (`@rory_runtime.checkpointed(...)`) or, if someone wrote it by
# hand, bare (`@rory_runtime.checkpointed`).
RORY_DECORATOR = m.Decorator(decorator=m.Call(func=IS_CHECKPOINTED) | IS_CHECKPOINTED)
# RORY's module call, alone on its line: `rory_runtime.checkpoint_module(__name__, ...)`.
RORY_MODULE_CALL_LINE = m.SimpleStatementLine(
    body=[m.Expr(value=m.Call(func=IS_CHECKPOINT_MODULE))]
)
# Exactly the line RORY adds: `import rory_runtime`.
RUNTIME_IMPORT_LINE = m.SimpleStatementLine(
    body=[m.Import(names=[m.ImportAlias(name=m.Name(RUNTIME_MODULE), asname=None)])]
)
# Any import of the module itself, possibly aliased: `import os, rory_runtime as rr`.
RUNTIME_IMPORT = m.Import(
    names=[m.ZeroOrMore(), m.ImportAlias(name=m.Name(RUNTIME_MODULE)), m.ZeroOrMore()]
)
# A line with such an import.
RUNTIME_IMPORT_STATEMENT = m.SimpleStatementLine(
    body=[m.ZeroOrMore(), RUNTIME_IMPORT, m.ZeroOrMore()]
)
# A line of the leading import block (`from __future__` included).
IMPORT_LINE = m.SimpleStatementLine(body=[m.AtLeastN(m.Import() | m.ImportFrom(), n=1)])
DOCSTRING_LINE = m.SimpleStatementLine(
    body=[m.Expr(value=m.SimpleString() | m.ConcatenatedString())]
)
# Top-level definitions; RORY's import must come before the first one to be usable there.
DEFINITION = m.ClassDef() | m.FunctionDef()


@dataclass(frozen=True)
class InstrumentedClass:
    """One node entry that was instrumented: a class decorated, or the module call added.

    Attributes:
        spec: Its keyvars.yaml entry (``spec.class_name`` is None for the module call).
        source_sha256: SHA-256 of the module's source with RORY's additions removed.
        manifest: The ``sha256:...`` digest written into the decorator or call.
    """

    spec: NodeSpec
    source_sha256: str
    manifest: str


@dataclass(frozen=True)
class InstrumentedModule:
    """The result of instrumenting one source file.

    Attributes:
        code: The new source, in the file's own encoding.
        classes: The entries instrumented, in keyvars.yaml order.
        warnings: Lines to show the user, ``file:line:col: warning: ...`` (clock reads RORY
            cannot replay, ``rory_instrument.clocks``).
    """

    code: bytes
    classes: tuple[InstrumentedClass, ...]
    warnings: tuple[str, ...] = ()


class StripRoryTransformer(cst.CSTTransformer):
    """Removes RORY's decorators, module calls and top-level ``import rory_runtime`` lines.

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
        # Only decorators were removed below, so the statements still align.
        pairs = zip(original_node.body, updated_node.body, strict=True)
        body = [
            updated
            for original, updated in pairs
            if not m.matches(updated, RUNTIME_IMPORT_LINE)
            and not m.matches(original, RORY_MODULE_CALL_LINE, metadata_resolver=self)
        ]
        return updated_node.with_changes(body=body)


def checkpoint_key(rule: FreshnessRule) -> str:
    """Returns the name a checkpoint stores the rule's variable under."""
    return CHECKPOINT_GLOBAL_PREFIX + rule.path if rule.module else rule.path


def freshness_argument(rules: Sequence[FreshnessRule]) -> FreshnessArgument:
    """Returns the ``freshness=`` value of RORY's calls for an entry's rules, in their order."""
    return tuple((checkpoint_key(rule), rule.max_age, rule.on_stale) for rule in rules)


def _tuple_source(items: Sequence[str]) -> str:
    """Returns a tuple display of already-written items, with the comma a single one needs."""
    return '(' + ', '.join(items) + (',' if len(items) == 1 else '') + ')'


def _arguments_source(
    vars: Sequence[str],
    manifest: str,
    *,
    module_vars: Sequence[str] = (),
    checkpoint_interval: float | None = None,
    replay: str | None = None,
    freshness: FreshnessArgument = (),
) -> str:
    """Returns the keyword arguments of RORY's calls, unset optional ones left out.

    Paths are identifiers joined by dots (a key adds ``global:``), actions and replay modes
    are fixed words and the digest is hex, so nothing needs escaping. Seconds are written as
    float reprs, which read back as the same float.
    """

    def names(values: Sequence[str]) -> str:
        return _tuple_source([f'"{v}"' for v in values])

    parts = [f'vars={names(vars)}']
    if module_vars:
        parts.append(f'module_vars={names(module_vars)}')
    if checkpoint_interval is not None:
        parts.append(f'checkpoint_interval={checkpoint_interval!r}')
    if replay is not None:
        parts.append(f'replay="{replay}"')
    if freshness:
        # float() so that a whole number of seconds is still written as a float (30.0).
        rules = [f'("{key}", {float(age)!r}, "{action}")' for key, age, action in freshness]
        parts.append(f'freshness={_tuple_source(rules)}')
    parts.append(f'manifest="{manifest}"')
    return ', '.join(parts)


def _parse_call(text: str) -> cst.Call:
    call = cst.parse_expression(text)
    assert isinstance(call, cst.Call)
    return call


def checkpointed_call(
    runtime: str,
    vars: Sequence[str],
    manifest: str,
    *,
    module_vars: Sequence[str] = (),
    checkpoint_interval: float | None = None,
    replay: str | None = None,
    freshness: FreshnessArgument = (),
) -> cst.Call:
    """Builds ``<runtime>.checkpointed(vars=(...), [module_vars=(...),] ..., manifest="...")``.

    Args:
        runtime: The name rory_runtime is bound to in the module.
        vars: Attribute paths below ``self``.
        manifest: The ``sha256:...`` digest.
        module_vars: Paths of module globals, if any.
        checkpoint_interval: Seconds between checkpoints, if set.
        replay: ``'paced'`` or ``'fast'``, if set.
        freshness: ``(checkpoint key, max_age, on_stale)`` per rule, if any
            (``freshness_argument``).

    Returns:
        The call expression; its keywords in the order of the parameters above, the
        digest last.
    """
    arguments = _arguments_source(
        vars, manifest, module_vars=module_vars, checkpoint_interval=checkpoint_interval,
        replay=replay, freshness=freshness,
    )
    return _parse_call(f'{runtime}.checkpointed({arguments})')


def checkpoint_module_call(
    runtime: str,
    vars: Sequence[str],
    manifest: str,
    *,
    checkpoint_interval: float | None = None,
    replay: str | None = None,
    freshness: FreshnessArgument = (),
) -> cst.Call:
    """Builds ``<runtime>.checkpoint_module(__name__, vars=(...), ..., manifest="...")``.

    Args:
        runtime: The name rory_runtime is bound to in the module.
        vars: Paths of the module globals.
        manifest: The ``sha256:...`` digest.
        checkpoint_interval: Seconds between checkpoints, if set.
        replay: ``'paced'`` or ``'fast'``, if set.
        freshness: ``(checkpoint key, max_age, on_stale)`` per rule, if any; the keys of
            module globals carry the ``global:`` prefix here too.

    Returns:
        The call expression.
    """
    arguments = _arguments_source(
        vars, manifest, checkpoint_interval=checkpoint_interval, replay=replay,
        freshness=freshness,
    )
    return _parse_call(f'{runtime}.checkpoint_module(__name__, {arguments})')


def _with_new_arguments(old: cst.Call, new: cst.Call) -> cst.Call:
    """Gives an existing RORY call the arguments of ``new``, keeping its spelling.

    With the same arguments (positional ones by position, keywords by name) only the values
    are swapped, so hand formatting of the call survives; otherwise the arguments are
    replaced.
    """

    def keys(call: cst.Call) -> list[str]:
        return [
            arg.keyword.value if arg.keyword is not None else f'#{i}'
            for i, arg in enumerate(call.args)
        ]

    values = dict(zip(keys(new), (arg.value for arg in new.args), strict=True))
    old_keys = keys(old)
    if sorted(old_keys) == sorted(values):
        args = [
            arg.with_changes(value=values[key])
            for arg, key in zip(old.args, old_keys, strict=True)
        ]
        return old.with_changes(args=args)
    # Other arguments: the new ones, laid out as RORY writes them.
    return old.with_changes(args=new.args, whitespace_before_args=new.whitespace_before_args)


def _with_new_decorator_arguments(decorator: cst.Decorator, new: cst.Call) -> cst.Decorator:
    """Gives an existing RORY decorator the arguments of ``new``, keeping its spelling."""
    old = decorator.decorator
    if not isinstance(old, cst.Call):
        return decorator.with_changes(decorator=new.with_changes(func=old))
    return decorator.with_changes(decorator=_with_new_arguments(old, new))


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
                decorators.append(_with_new_decorator_arguments(updated, call))
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


def module_call_index(body: Sequence[cst.BaseStatement]) -> int:
    """Returns where RORY's module call goes: after the leading imports and the runtime's.

    ``import rory_runtime`` is either among the leading imports or added at their end
    (``EnsureRuntimeImportTransformer``, run after this), so the call directly follows it.
    """
    index = import_insertion_index(body)
    for position, statement in enumerate(body):
        if m.matches(statement, DEFINITION):
            break
        if m.matches(statement, RUNTIME_IMPORT_STATEMENT):
            return max(index, position + 1)
    return index


class CheckpointModuleTransformer(cst.CSTTransformer):
    """Puts ``<runtime>.checkpoint_module(__name__, vars=..., manifest=...)`` at module level.

    A module without the call gets it at ``module_call_index``, the line right after
    ``import rory_runtime``; a module that has it (a line of its own at module level, found
    by qualified name) gets its arguments replaced where it is, and any second copy dropped.

    Args:
        call: The call, spelled with the name rory_runtime is bound to in the module.
    """

    METADATA_DEPENDENCIES = (QualifiedNameProvider,)

    def __init__(self, call: cst.Call) -> None:
        super().__init__()
        self.call = call
        self.added = False

    def leave_Module(self, original_node: cst.Module, updated_node: cst.Module) -> cst.Module:
        body: list[cst.BaseStatement] = []
        found = False
        # No statement is transformed below the module, so original and updated align.
        for original, updated in zip(original_node.body, updated_node.body, strict=True):
            if not m.matches(original, RORY_MODULE_CALL_LINE, metadata_resolver=self):
                body.append(updated)
            elif not found:
                assert isinstance(updated, cst.SimpleStatementLine)
                (expr,) = updated.body
                assert isinstance(expr, cst.Expr) and isinstance(expr.value, cst.Call)
                new = expr.with_changes(value=_with_new_arguments(expr.value, self.call))
                body.append(updated.with_changes(body=[new]))
                found = True
        if not found:
            line = cst.SimpleStatementLine(body=[cst.Expr(value=self.call)])
            body.insert(module_call_index(body), line)
            self.added = True
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


def _digest(spec: NodeSpec, file: str, digest: str) -> str:
    return manifest_digest(
        file=file, class_name=spec.class_name, vars=spec.vars, source_sha256=digest,
        module_vars=spec.module_vars,
    )


def instrument_source(
    source: bytes | str,
    keyvars: KeyVars,
    file: str,
    *,
    display: str | None = None,
    specs: Sequence[NodeSpec] | None = None,
    resolve: BaseResolver | None = None,
) -> InstrumentedModule:
    """Instruments the nodes that keyvars.yaml lists for one file.

    Args:
        source: The file's content.
        keyvars: The configuration; names keyvars.yaml in messages.
        file: The file's path relative to SRC, POSIX separators, as in the manifest.
        display: How to name the file in messages; defaults to ``file``.
        specs: The entries to apply; defaults to those of ``keyvars`` whose ``file`` is
            ``file`` (the tree step passes them itself once it has resolved paths).
        resolve: Finds base classes in other files of SRC (the tree step passes it); None
            to look for them in this file only.

    Returns:
        The new source and what was instrumented. With no entries for ``file`` the source
        is returned unchanged.

    Raises:
        SourceError: The file is not valid Python, or a check of ``rory_instrument.checks``
            fails in the source.
        ConfigError: A listed class or module variable is not in the file.
    """
    raw = source.encode('utf-8') if isinstance(source, str) else source
    if specs is None:
        specs = [s for s in keyvars.nodes if s.file == file]
    shown = file if display is None else display
    if not specs:
        return InstrumentedModule(raw, ())
    module = parse_source(raw, shown)
    wrapper = MetadataWrapper(module)
    checker = SpecChecker(keyvars, collect_module(wrapper, file, shown), resolve)
    for spec in specs:
        checker.check(spec)
    check_entities(wrapper, shown, [spec.class_name for spec in specs])

    warnings = wall_clock_warnings(wrapper, shown)
    digest = source_sha256(wrapper)
    binding = runtime_binding(wrapper.module)
    runtime = binding or RUNTIME_MODULE
    done: list[InstrumentedClass] = []
    calls: dict[str, cst.Call] = {}
    module_call: cst.Call | None = None
    for spec in specs:
        manifest = _digest(spec, file, digest)
        done.append(InstrumentedClass(spec, digest, manifest))
        interval, replay = spec.checkpoint_interval, spec.replay
        freshness = freshness_argument(spec.freshness)
        if spec.class_name is None:
            module_call = checkpoint_module_call(
                runtime, spec.module_vars, manifest, checkpoint_interval=interval,
                replay=replay, freshness=freshness,
            )
        else:
            calls[spec.class_name] = checkpointed_call(
                runtime, spec.vars, manifest, module_vars=spec.module_vars,
                checkpoint_interval=interval, replay=replay, freshness=freshness,
            )

    added = False
    if module_call is not None:
        place = CheckpointModuleTransformer(module_call)
        wrapper = MetadataWrapper(wrapper.visit(place))
        added = place.added
    decorate = CheckpointDecoratorTransformer(calls)
    result = wrapper.visit(decorate)
    if (decorate.added or added) and binding is None:
        result = result.visit(EnsureRuntimeImportTransformer())
    return InstrumentedModule(result.bytes, tuple(done), warnings)
