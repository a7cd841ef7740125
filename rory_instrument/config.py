"""Reading keyvars.yaml: which nodes to instrument and which variables make up their state.

The file is parsed with ``yaml.compose`` rather than ``yaml.safe_load`` so that every value
keeps its source position; each error then points at the offending line and column of
keyvars.yaml. The shape is::

    nodes:
      - file: integrator.py        # relative to SRC
        class: Integrator          # dotted for nested classes: Outer.Inner
        vars:                      # self.<path> attributes; dotted paths reach inside
          - total
          - ekf.P
          - {name: goal, max_age: 30, on_stale: refuse}   # a freshness rule
        module_vars: [counter]     # optional: module globals (nodes written as functions)
        checkpoint_interval: 0.5   # optional, seconds
        replay: paced              # optional, 'paced' or 'fast'

An entry names ``class`` with ``vars``, or ``module_vars``, or both (a class may then leave
out ``vars``). An entry of either list is a path, or a mapping with the path as ``name`` and
optionally ``max_age`` (seconds) and ``on_stale`` (``reset``, the default, ``keep`` or
``refuse``): what the runtime does with the variable when the checkpoint it comes from is
older than ``max_age``. Plain scalars are typed as YAML 1.2 (the core schema editors use), so
``vars: [on]`` names an attribute ``on`` while ``file: 123`` is a number, not a path.
``keyvars.schema.json`` next to this module describes the same shape as a JSON Schema for
editors; this parser stays the authority, for its ``file:line:col`` messages and the rules a
schema cannot say (duplicate entries and keys, overlapping paths, Python identifiers).

Adding a per-node key means adding one parser to ``_NODE_FIELDS``, one field to ``NodeSpec``
and one property to the schema.
"""

from __future__ import annotations

import json
import keyword
import math
import posixpath
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, cast

import yaml

from rory_instrument.errors import ConfigError

REPLAY_MODES = ('paced', 'fast')
# What a freshness rule does with a variable whose checkpoint is too old; the first is the
# default.
STALE_ACTIONS = ('reset', 'keep', 'refuse')
# The keys of an entry of ``vars`` or ``module_vars`` written as a mapping.
_PATH_ENTRY_FIELDS = ('name', 'max_age', 'on_stale')
# The JSON Schema of keyvars.yaml, shipped next to this module.
SCHEMA_NAME = 'keyvars.schema.json'

# YAML 1.2 core schema: the plain scalars that are not strings.
_YAML12_NULL = re.compile(r'~|null|Null|NULL|')
_YAML12_BOOL = re.compile(r'true|True|TRUE|false|False|FALSE')
_YAML12_INT = re.compile(r'[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+')
_YAML12_FLOAT = re.compile(
    r'[-+]?(\.[0-9]+|[0-9]+(\.[0-9]*)?)([eE][-+]?[0-9]+)?|[-+]?\.(inf|Inf|INF)|\.(nan|NaN|NAN)'
)


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
class FreshnessRule:
    """How old a checkpointed variable may be when it is restored, and what happens if older.

    Attributes:
        path: The variable's path, as listed in ``vars`` or ``module_vars``.
        max_age: Seconds since the checkpoint was taken, on the clock the node uses.
        on_stale: ``'reset'``, ``'keep'`` or ``'refuse'`` (see ``STALE_ACTIONS``).
        module: True for an entry of ``module_vars``, False for one of ``vars``.
    """

    path: str
    max_age: float
    on_stale: str
    module: bool


@dataclass(frozen=True)
class NodeSpec:
    """One entry of ``nodes:``: a node to instrument and the variables it checkpoints.

    Attributes:
        index: Position in the ``nodes`` list, used to name fields in messages.
        file: Source file relative to SRC, as written (normalised, POSIX separators).
        class_name: Dotted class name inside ``file`` (``Outer.Inner`` for nested classes),
            or None for a node written as functions (then ``module_vars`` is set).
        vars: Attribute paths below ``self`` to checkpoint (``total``, ``ekf.P``), in the
            given order; empty when ``class_name`` is None.
        checkpoint_interval: Seconds between checkpoints, or None for the runtime default.
        replay: ``'paced'`` or ``'fast'``, or None for the runtime default.
        module_vars: Paths of module globals to checkpoint (``counter``, ``state.pose``).
        freshness: The rules of the entries that set ``max_age``: those of ``vars`` in
            order, then those of ``module_vars``.
        marks: Position of each field, keyed by its path below the node (``''`` for the
            node itself, ``'class'``, ``'vars'``, ``'vars[2]'``, ``'module_vars[0]'``,
            ``'vars[2].max_age'``...). ``'vars[2]'`` is where the path is written, also in
            the mapping form, so that messages about the path point at it. Not compared.
    """

    index: int
    file: str
    class_name: str | None
    vars: tuple[str, ...]
    checkpoint_interval: float | None = None
    replay: str | None = None
    module_vars: tuple[str, ...] = ()
    freshness: tuple[FreshnessRule, ...] = ()
    marks: Mapping[str, Mark] = field(default_factory=dict, compare=False, repr=False)

    @property
    def label(self) -> str:
        """Returns how messages and the command line name the entry: ``file:Class`` or ``file``."""
        return self.file if self.class_name is None else f'{self.file}:{self.class_name}'

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


def keyvars_schema() -> dict[str, Any]:
    """Returns the JSON Schema of keyvars.yaml shipped with the package (draft 2020-12)."""
    text = resources.files(__package__).joinpath(SCHEMA_NAME).read_text(encoding='utf-8')
    return cast(dict[str, Any], json.loads(text))


def yaml12_type(node: yaml.ScalarNode) -> str | None:
    """Returns what a scalar is under the YAML 1.2 core schema when it is not a string.

    PyYAML types plain scalars by YAML 1.1 (``on`` is a boolean there); editors and JSON
    Schema validators see YAML 1.2, where only these plain forms are not strings.

    Args:
        node: A composed scalar.

    Returns:
        ``'null'``, ``'the boolean <text>'`` or ``'the number <text>'``, or None for a string
        (every quoted or block scalar, and every other plain one).
    """
    if node.style is not None:
        return None
    text = str(node.value)
    if _YAML12_NULL.fullmatch(text):
        return 'null'
    if _YAML12_BOOL.fullmatch(text):
        return f'the boolean {text}'
    if _YAML12_INT.fullmatch(text) or _YAML12_FLOAT.fullmatch(text):
        return f'the number {text}'
    return None


def yaml12_number(node: yaml.ScalarNode) -> float | None:
    """Returns a plain scalar's value if it is a number under the YAML 1.2 core schema."""
    text = str(node.value)
    if node.style is not None:
        return None
    if _YAML12_INT.fullmatch(text):
        return float(int(text, 0) if text[:2] in ('0o', '0x') else int(text))
    if _YAML12_FLOAT.fullmatch(text):
        return float(text.lower().replace('.inf', 'inf').replace('.nan', 'nan'))
    return None


def one_of(options: tuple[str, ...]) -> str:
    """Returns the options quoted for a message: ``'a', 'b' or 'c'``."""
    quoted = [repr(option) for option in options]
    return ', '.join(quoted[:-1]) + ' or ' + quoted[-1] if len(quoted) > 1 else quoted[0]


def path_overlap(first: str, second: str) -> bool:
    """Returns whether one attribute path is the other or lies inside it (``ekf``, ``ekf.P``)."""
    a, b = first.split('.'), second.split('.')
    n = min(len(a), len(b))
    return a[:n] == b[:n]


@dataclass(frozen=True)
class _ListedPaths:
    """The parsed value of ``vars`` or ``module_vars``, before it is split into NodeSpec."""

    names: tuple[str, ...]
    rules: tuple[FreshnessRule, ...]


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
        first: dict[tuple[str, str | None], NodeSpec] = {}
        for spec in specs:
            key = (spec.file, spec.class_name)
            if key in first:
                line = first[key].mark().line
                what = 'entry' if spec.class_name is not None else 'module_vars entry'
                raise self.fail(
                    spec.mark(),
                    f'{spec.field_path()}: duplicate {what} for {spec.label} '
                    f'(first at line {line})',
                )
            first[key] = spec
        return KeyVars(self.path, specs)

    def node(self, index: int, node: yaml.Node) -> NodeSpec:
        where = f'nodes[{index}]'
        items = self.mapping(node, where, tuple(_NODE_FIELDS), _REQUIRED_NODE_FIELDS)
        self.node_shape(node, where, items)
        marks: dict[str, Mark] = {'': Mark.of(node)}
        values: dict[str, Any] = {'class_name': None, 'vars': ()}
        for name, (_key, value) in items.items():
            marks[name] = Mark.of(value)
            values[_NODE_FIELD_ATTRS.get(name, name)] = _NODE_FIELDS[name](
                self, value, f'{where}.{name}', marks
            )
        return NodeSpec(index=index, marks=marks, **_split_listed_paths(values))

    def node_shape(
        self, node: yaml.Node, where: str, items: Mapping[str, tuple[yaml.Node, yaml.Node]]
    ) -> None:
        """Requires ``class`` with ``vars``, or ``module_vars``, or both."""
        if 'vars' in items and 'class' not in items:
            raise self.fail(node, f"{where}: missing required key 'class'")
        if 'module_vars' in items:
            return
        if 'class' in items and 'vars' not in items:
            raise self.fail(node, f"{where}: missing required key 'vars'")
        if 'class' not in items:
            raise self.fail(
                node,
                f"{where}: expected 'class' and 'vars' (a Node subclass and its attributes), "
                "'module_vars' (module globals), or both",
            )

    def text(self, node: yaml.Node, where: str, what: str) -> str:
        """Returns a string scalar's text as written.

        The raw text is used instead of PyYAML's implicit typing, which follows YAML 1.1 and
        would turn an attribute named ``on`` or ``yes`` into a boolean; a plain scalar that
        YAML 1.2 reads as null, a boolean or a number is refused, as the schema does.
        """
        if not isinstance(node, yaml.ScalarNode) or not node.value:
            raise self.fail(node, f'{where}: expected {what}')
        other = yaml12_type(node)
        if other is not None:
            raise self.fail(node, f'{where}: expected {what}, got {other} (quote it if it is '
                            'meant as a name)')
        return str(node.value)

    def attribute_path(self, node: yaml.Node, where: str) -> str:
        """Returns an attribute path: identifiers separated by dots (``total``, ``ekf.P``)."""
        name = self.text(node, where, 'an attribute name')
        parts = name.split('.')
        if all(part.isidentifier() and not keyword.iskeyword(part) for part in parts):
            return name
        if len(parts) == 1:
            raise self.fail(node, f'{where}: {name!r} is not a Python identifier')
        raise self.fail(node, f'{where}: {name!r} is not an attribute path (Python '
                        'identifiers separated by dots, e.g. ekf.P)')

    def seconds(self, node: yaml.Node, where: str) -> float:
        """Returns a positive, finite YAML 1.2 number (a quoted one is a string)."""
        problem = f'{where}: expected a positive number of seconds'
        if not isinstance(node, yaml.ScalarNode):
            raise self.fail(node, problem)
        # Quoted scalars are strings even when they look like numbers.
        if node.style is not None:
            raise self.fail(node, f'{problem}, got the string {node.value!r}')
        value = yaml12_number(node)
        if value is None or not math.isfinite(value) or value <= 0:
            raise self.fail(node, f'{problem}, got {node.value!r}')
        return value

    def choice(self, node: yaml.Node, where: str, options: tuple[str, ...]) -> str:
        """Returns a string that is one of ``options``, exactly as spelled there."""
        expected = one_of(options)
        value = self.text(node, where, expected)
        if value not in options:
            raise self.fail(node, f'{where}: expected {expected}, got {value!r}')
        return value

    def paths(
        self, node: yaml.Node, where: str, marks: dict[str, Mark], key: str
    ) -> _ListedPaths:
        """Returns a non-empty list of distinct, non-overlapping attribute paths and their rules.

        Plain entries and mapping entries are one list: a path may not appear twice or
        inside another whichever way each is written.
        """
        if not isinstance(node, yaml.SequenceNode) or not node.value:
            raise self.fail(node, f'{where}: expected a non-empty list of attribute names')
        names: list[str] = []
        rules: list[FreshnessRule] = []
        module = key == 'module_vars'
        for i, item in enumerate(node.value):
            name, rule = self.path_entry(item, f'{where}[{i}]', marks, f'{key}[{i}]', module)
            at = marks[f'{key}[{i}]']
            if name in names:
                raise self.fail(at, f'{where}[{i}]: duplicate var {name!r}')
            for j, other in enumerate(names):
                if path_overlap(name, other):
                    raise self.fail(
                        at,
                        f'{where}[{i}]: {name!r} overlaps {other!r} ({key}[{j}]); list either '
                        'the whole object or parts of it',
                    )
            names.append(name)
            if rule is not None:
                rules.append(rule)
        return _ListedPaths(tuple(names), tuple(rules))

    def path_entry(
        self, item: yaml.Node, where: str, marks: dict[str, Mark], key: str, module: bool
    ) -> tuple[str, FreshnessRule | None]:
        """Returns the path of one list entry, and its rule if it is a mapping with max_age.

        Records ``marks[key]`` where the path is written, and ``marks[key + '.max_age']``
        and the like for the keys of a mapping.
        """
        if isinstance(item, yaml.SequenceNode):
            raise self.fail(item, f'{where}: expected an attribute name or a mapping with keys '
                            f'{", ".join(_PATH_ENTRY_FIELDS)}')
        if not isinstance(item, yaml.MappingNode):
            marks[key] = Mark.of(item)
            return self.attribute_path(item, where), None
        fields = self.mapping(item, where, _PATH_ENTRY_FIELDS, ('name',))
        for name, (_key, value) in fields.items():
            marks[f'{key}.{name}'] = Mark.of(value)
        marks[key] = marks[f'{key}.name']
        path = self.attribute_path(fields['name'][1], f'{where}.name')
        return path, self.freshness_rule(path, fields, where, module)

    def freshness_rule(
        self, path: str, fields: Mapping[str, tuple[yaml.Node, yaml.Node]], where: str,
        module: bool,
    ) -> FreshnessRule | None:
        """Returns the rule of a mapping entry, or None when it sets no ``max_age``."""
        stale = fields.get('on_stale')
        if 'max_age' not in fields:
            if stale is not None:
                # Refused rather than ignored: the author meant a rule that would never apply.
                raise self.fail(stale[0], f'{where}.on_stale: needs max_age; without it the '
                                'variable is never stale')
            return None
        max_age = self.seconds(fields['max_age'][1], f'{where}.max_age')
        action = STALE_ACTIONS[0]
        if stale is not None:
            action = self.choice(stale[1], f'{where}.on_stale', STALE_ACTIONS)
        return FreshnessRule(path, max_age, action, module)


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
) -> _ListedPaths:
    return p.paths(node, where, marks, 'vars')


def _parse_module_vars(
    p: _Parser, node: yaml.Node, where: str, marks: dict[str, Mark]
) -> _ListedPaths:
    return p.paths(node, where, marks, 'module_vars')


def _parse_interval(p: _Parser, node: yaml.Node, where: str, marks: dict[str, Mark]) -> float:
    return p.seconds(node, where)


def _parse_replay(p: _Parser, node: yaml.Node, where: str, marks: dict[str, Mark]) -> str:
    return p.choice(node, where, REPLAY_MODES)


def _split_listed_paths(values: dict[str, Any]) -> dict[str, Any]:
    """Turns the parsed ``vars`` and ``module_vars`` into NodeSpec's paths and ``freshness``.

    The rules of ``vars`` come first whatever order the keys were written in, so that the
    same entries always give the same decorator.
    """
    fields = dict(values)
    rules: list[FreshnessRule] = []
    for name in ('vars', 'module_vars'):
        listed = fields.get(name)
        if isinstance(listed, _ListedPaths):
            fields[name] = listed.names
            rules.extend(listed.rules)
    fields['freshness'] = tuple(rules)
    return fields


# Every key a node entry may have, in the order messages list them.
_NODE_FIELDS: dict[str, _FieldParser] = {
    'file': _parse_file,
    'class': _parse_class,
    'vars': _parse_vars,
    'module_vars': _parse_module_vars,
    'checkpoint_interval': _parse_interval,
    'replay': _parse_replay,
}
# 'class', 'vars' and 'module_vars' are required in combinations; see _Parser.node_shape.
_REQUIRED_NODE_FIELDS = ('file',)
# YAML keys whose NodeSpec attribute is spelled differently ('class' is a keyword).
_NODE_FIELD_ATTRS = {'class': 'class_name'}
