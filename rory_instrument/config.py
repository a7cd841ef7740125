"""Reading keyvars.yaml: which node classes to instrument and which attributes they keep.

The file is parsed with ``yaml.compose`` rather than ``yaml.safe_load`` so that every value
keeps its source position; each error then points at the offending line and column of
keyvars.yaml. The shape is::

    nodes:
      - file: integrator.py        # relative to SRC
        class: Integrator          # dotted for nested classes: Outer.Inner
        vars: [total, count, history]
        checkpoint_interval: 0.5   # optional, seconds
        replay: paced              # optional, 'paced' or 'fast'

Adding a per-node key means adding one parser to ``_NODE_FIELDS`` and one field to
``NodeSpec``; nothing else changes.
"""

from __future__ import annotations

import keyword
import math
import posixpath
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from rory_instrument.errors import ConfigError

REPLAY_MODES = ('paced', 'fast')


@dataclass(frozen=True)
class Mark:
    """A 1-based position in keyvars.yaml.

    Attributes:
        line: 1-based line.
        col: 1-based column.
    """

    line: int
    col: int

    @classmethod
    def of(cls, node: yaml.Node) -> Mark:
        """Returns the start position of a composed YAML node (PyYAML counts from 0)."""
        return cls(node.start_mark.line + 1, node.start_mark.column + 1)


@dataclass(frozen=True)
class NodeSpec:
    """One entry of ``nodes:``: a class to instrument and the attributes it checkpoints.

    Attributes:
        index: Position in the ``nodes`` list, used to name fields in messages.
        file: Source file relative to SRC, as written (normalised, POSIX separators).
        class_name: Dotted class name inside ``file`` (``Outer.Inner`` for nested classes).
        vars: Names of the ``self.<name>`` attributes to checkpoint, in the given order.
        checkpoint_interval: Seconds between checkpoints, or None for the runtime default.
        replay: ``'paced'`` or ``'fast'``, or None for the runtime default.
        marks: Position of each field, keyed by its path below the node (``''`` for the
            node itself, ``'class'``, ``'vars'``, ``'vars[2]'``...). Not compared.
    """

    index: int
    file: str
    class_name: str
    vars: tuple[str, ...]
    checkpoint_interval: float | None = None
    replay: str | None = None
    marks: Mapping[str, Mark] = field(default_factory=dict, compare=False, repr=False)

    def field_path(self, name: str = '') -> str:
        """Returns the dotted path of a field for messages, e.g. ``nodes[0].vars``."""
        return f'nodes[{self.index}]' + (f'.{name}' if name else '')

    def mark(self, name: str = '') -> Mark:
        """Returns where field ``name`` is, falling back to the node's own position."""
        return self.marks.get(name) or self.marks.get('') or Mark(0, 0)


@dataclass(frozen=True)
class KeyVars:
    """The whole of keyvars.yaml.

    Attributes:
        path: The file as named on the command line; prefixes every message about it.
        nodes: The node entries in file order.
    """

    path: str
    nodes: tuple[NodeSpec, ...]

    def error(self, spec: NodeSpec, name: str, message: str) -> ConfigError:
        """Builds an error located at field ``name`` of ``spec``.

        Args:
            spec: The node entry the problem is in.
            name: Field below the node (see ``NodeSpec.marks``), ``''`` for the node.
            message: What is wrong.

        Returns:
            The error, for the caller to raise.
        """
        mark = spec.mark(name)
        return ConfigError(self.path, mark.line, mark.col, message)


def load_keyvars(path: Path | str, display: str | None = None) -> KeyVars:
    """Reads and validates keyvars.yaml.

    Args:
        path: The file to read.
        display: How to name the file in messages; defaults to ``str(path)``.

    Returns:
        The validated configuration.

    Raises:
        ConfigError: The file is unreadable, not YAML, or not of the expected shape.
    """
    shown = str(path) if display is None else display
    try:
        text = Path(path).read_text(encoding='utf-8')
    except (OSError, UnicodeDecodeError) as e:
        reason = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        raise ConfigError(shown, 0, 0, f'cannot read keyvars file: {reason}') from e
    return parse_keyvars(text, shown)


def parse_keyvars(text: str, path: str) -> KeyVars:
    """Validates the text of keyvars.yaml.

    Args:
        text: The YAML document.
        path: How to name the file in messages.

    Returns:
        The validated configuration.

    Raises:
        ConfigError: The text is not YAML or not of the expected shape.
    """
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark is not None else (0, 0)
        problem = ' '.join(p for p in (e.context, e.problem) if p)
        raise ConfigError(path, line, col, f'not valid YAML: {problem}') from e
    except yaml.YAMLError as e:
        raise ConfigError(path, 0, 0, f'not valid YAML: {e}') from e
    return _Parser(path).keyvars(root)


# Parses the value of one node field; returns the value to store in NodeSpec.
_FieldParser = Callable[['_Parser', yaml.Node, str, dict[str, Mark]], Any]


class _Parser:
    """Walks the composed YAML tree, raising ConfigError at the first problem."""

    def __init__(self, path: str) -> None:
        self.path = path

    def fail(self, node: yaml.Node | Mark, message: str) -> ConfigError:
        mark = node if isinstance(node, Mark) else Mark.of(node)
        return ConfigError(self.path, mark.line, mark.col, message)

    def mapping(
        self, node: yaml.Node, where: str, allowed: tuple[str, ...], required: tuple[str, ...]
    ) -> dict[str, tuple[yaml.Node, yaml.Node]]:
        """Returns the (key node, value node) of each key, rejecting unknown and duplicates."""
        expected = ', '.join(allowed)
        if not isinstance(node, yaml.MappingNode):
            raise self.fail(node, f'{where}: expected a mapping with keys {expected}')
        items: dict[str, tuple[yaml.Node, yaml.Node]] = {}
        for key, value in node.value:
            if not isinstance(key, yaml.ScalarNode):
                raise self.fail(key, f'{where}: keys must be plain names')
            if key.value not in allowed:
                raise self.fail(key, f'{where}: unknown key {key.value!r} (expected: {expected})')
            if key.value in items:
                raise self.fail(key, f'{where}: duplicate key {key.value!r}')
            items[key.value] = (key, value)
        for name in required:
            if name not in items:
                raise self.fail(node, f'{where}: missing required key {name!r}')
        return items

    def keyvars(self, root: yaml.Node | None) -> KeyVars:
        if root is None:
            raise self.fail(Mark(1, 1), "expected a mapping with key 'nodes', got an empty file")
        items = self.mapping(root, 'top level', ('nodes',), ('nodes',))
        nodes = items['nodes'][1]
        if not isinstance(nodes, yaml.SequenceNode) or not nodes.value:
            raise self.fail(nodes, 'nodes: expected a non-empty list of node entries')
        specs = tuple(self.node(i, n) for i, n in enumerate(nodes.value))
        first: dict[tuple[str, str], NodeSpec] = {}
        for spec in specs:
            key = (spec.file, spec.class_name)
            if key in first:
                line = first[key].mark().line
                raise self.fail(
                    spec.mark(),
                    f'{spec.field_path()}: duplicate entry for {spec.file}:{spec.class_name} '
                    f'(first at line {line})',
                )
            first[key] = spec
        return KeyVars(self.path, specs)

    def node(self, index: int, node: yaml.Node) -> NodeSpec:
        where = f'nodes[{index}]'
        items = self.mapping(node, where, tuple(_NODE_FIELDS), _REQUIRED_NODE_FIELDS)
        marks: dict[str, Mark] = {'': Mark.of(node)}
        values: dict[str, Any] = {}
        for name, (_key, value) in items.items():
            marks[name] = Mark.of(value)
            values[_NODE_FIELD_ATTRS.get(name, name)] = _NODE_FIELDS[name](
                self, value, f'{where}.{name}', marks
            )
        return NodeSpec(index=index, marks=marks, **values)

    def text(self, node: yaml.Node, where: str, what: str) -> str:
        """Returns a scalar's text as written.

        The raw text is used instead of PyYAML's implicit typing, which would turn an
        attribute named ``on`` or ``yes`` into a boolean.
        """
        if not isinstance(node, yaml.ScalarNode) or not node.value:
            raise self.fail(node, f'{where}: expected {what}')
        return str(node.value)

    def identifier(self, node: yaml.Node, where: str) -> str:
        name = self.text(node, where, 'an attribute name')
        if not name.isidentifier() or keyword.iskeyword(name):
            raise self.fail(node, f'{where}: {name!r} is not a Python identifier')
        return name


def _parse_file(p: _Parser, node: yaml.Node, where: str, marks: dict[str, Mark]) -> str:
    raw = p.text(node, where, 'a path relative to SRC')
    # Normalised so that 'a.py' and './a.py' are the same entry; the tree step checks that
    # it stays inside SRC.
    return posixpath.normpath(raw.replace('\\', '/'))


def _parse_class(p: _Parser, node: yaml.Node, where: str, marks: dict[str, Mark]) -> str:
    name = p.text(node, where, 'a class name')
    if not all(part.isidentifier() and not keyword.iskeyword(part) for part in name.split('.')):
        raise p.fail(node, f'{where}: {name!r} is not a class name (use Outer.Inner if nested)')
    return name


def _parse_vars(
    p: _Parser, node: yaml.Node, where: str, marks: dict[str, Mark]
) -> tuple[str, ...]:
    if not isinstance(node, yaml.SequenceNode) or not node.value:
        raise p.fail(node, f'{where}: expected a non-empty list of attribute names')
    names: list[str] = []
    for i, item in enumerate(node.value):
        marks[f'vars[{i}]'] = Mark.of(item)
        name = p.identifier(item, f'{where}[{i}]')
        if name in names:
            raise p.fail(item, f'{where}[{i}]: duplicate var {name!r}')
        names.append(name)
    return tuple(names)


def _parse_interval(p: _Parser, node: yaml.Node, where: str, marks: dict[str, Mark]) -> float:
    problem = f'{where}: expected a positive number of seconds'
    if not isinstance(node, yaml.ScalarNode):
        raise p.fail(node, problem)
    # Quoted scalars are strings even when they look like numbers.
    if node.style is not None:
        raise p.fail(node, f'{problem}, got the string {node.value!r}')
    try:
        value = float(node.value)
    except ValueError:
        raise p.fail(node, f'{problem}, got {node.value!r}') from None
    if not math.isfinite(value) or value <= 0:
        raise p.fail(node, f'{problem}, got {node.value!r}')
    return value


def _parse_replay(p: _Parser, node: yaml.Node, where: str, marks: dict[str, Mark]) -> str:
    modes = ' or '.join(repr(m) for m in REPLAY_MODES)
    value = p.text(node, where, modes)
    if value not in REPLAY_MODES:
        raise p.fail(node, f'{where}: expected {modes}, got {value!r}')
    return value


# Every key a node entry may have, in the order messages list them.
_NODE_FIELDS: dict[str, _FieldParser] = {
    'file': _parse_file,
    'class': _parse_class,
    'vars': _parse_vars,
    'checkpoint_interval': _parse_interval,
    'replay': _parse_replay,
}
_REQUIRED_NODE_FIELDS = ('file', 'class', 'vars')
# YAML keys whose NodeSpec attribute is spelled differently ('class' is a keyword).
_NODE_FIELD_ATTRS = {'class': 'class_name'}
