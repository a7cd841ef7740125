"""An instrumented package needs RORY's runtime: say so where the package says what it needs.

A ROS 2 ``ament_python`` package (or any Python package) copied by ``rory-instrument`` gets
:data:`DISTRIBUTION` added, in OUT only, to:

* ``package.xml``: an ``<exec_depend>`` (what ``rosdep`` and colcon read);
* ``setup.py``: the ``install_requires`` of its ``setup(...)`` call (libcst, so the rest of
  the file is byte for byte the same);
* ``setup.cfg``: ``install_requires`` under ``[options]``;
* ``pyproject.toml``: ``dependencies`` under ``[project]``.

Each edit is idempotent (a package that lists it already is left alone), keeps the file's
formatting, and is skipped with a warning where the file computes the list instead of
writing it out.
"""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import libcst as cst
import libcst.matchers as m

DISTRIBUTION = 'rory-ros2'

# `setup(...)` or `setuptools.setup(...)`, as setup.py files write it.
SETUP_CALL = m.Call(func=m.Name('setup') | m.Attribute(attr=m.Name('setup')))
_REQUIREMENT_NAME = re.compile(r'\s*([A-Za-z0-9][A-Za-z0-9._-]*)')


def _names(requirements: list[str]) -> set[str]:
    """Normalised distribution names of requirement strings (``rory_ros2>=0.1`` ->
    ``rory-ros2``)."""
    found = set()
    for requirement in requirements:
        match = _REQUIREMENT_NAME.match(requirement)
        if match:
            found.add(re.sub(r'[-_.]+', '-', match.group(1)).lower())
    return found


def add_to_package_xml(text: str) -> str | None:
    """package.xml with an ``<exec_depend>`` on RORY, or None when it has one (or no
    ``</package>`` to put it before)."""
    if re.search(rf'<exec_depend>\s*{re.escape(DISTRIBUTION)}\s*</exec_depend>', text):
        return None
    line = f'<exec_depend>{DISTRIBUTION}</exec_depend>'
    found = list(re.finditer(r'^([ \t]*)<exec_depend>.*?</exec_depend>[ \t]*\n', text, re.M))
    if found:
        last = found[-1]
        return f'{text[:last.end()]}{last.group(1)}{line}\n{text[last.end():]}'
    anchor = re.search(r'^([ \t]*)(<export>|</package>)', text, re.M)
    if anchor is None:
        return None
    indent = anchor.group(1) or '  '
    return f'{text[:anchor.start()]}{indent}{line}\n{text[anchor.start():]}'


class _AddInstallRequires(cst.CSTTransformer):
    """Adds the distribution to ``install_requires=[...]`` of the ``setup(...)`` call."""

    def __init__(self) -> None:
        super().__init__()
        self.changed = False
        self.computed = False  # install_requires is not a literal list: left alone

    def leave_Call(self, original_node: cst.Call, updated_node: cst.Call) -> cst.Call:
        if not m.matches(updated_node, SETUP_CALL):
            return updated_node
        new = cst.SimpleString(f"'{DISTRIBUTION}'")
        args = list(updated_node.args)
        for i, arg in enumerate(args):
            if arg.keyword is None or arg.keyword.value != 'install_requires':
                continue
            value = arg.value
            if not isinstance(value, cst.List | cst.Tuple):
                self.computed = True
                return updated_node
            listed = [e.value.evaluated_value for e in value.elements
                      if isinstance(e, cst.Element) and isinstance(e.value, cst.SimpleString)]
            if DISTRIBUTION in _names([v for v in listed if isinstance(v, str)]):
                return updated_node
            elements = list(value.elements)
            if elements:
                last = elements[-1]
                elements[-1] = last.with_changes(comma=cst.Comma(
                    whitespace_after=cst.SimpleWhitespace(' ')))
            elements.append(cst.Element(new))
            args[i] = arg.with_changes(value=value.with_changes(elements=elements))
            self.changed = True
            return updated_node.with_changes(args=args)
        comma = cst.Comma(whitespace_after=cst.SimpleWhitespace(' '))
        if args:
            args[-1] = args[-1].with_changes(comma=comma)
        args.append(cst.Arg(keyword=cst.Name('install_requires'),
                            value=cst.List([cst.Element(new)]),
                            equal=cst.AssignEqual(cst.SimpleWhitespace(''),
                                                  cst.SimpleWhitespace(''))))
        self.changed = True
        return updated_node.with_changes(args=args)


def add_to_setup_py(text: str) -> tuple[str | None, bool]:
    """setup.py with RORY in ``install_requires``; None when unchanged. The flag: the list is
    computed, so nothing was added."""
    try:
        module = cst.parse_module(text)
    except cst.ParserSyntaxError:
        return None, False
    adder = _AddInstallRequires()
    result = module.visit(adder)
    return (result.code if adder.changed else None), adder.computed


def add_to_setup_cfg(text: str) -> str | None:
    """setup.cfg with RORY in ``[options] install_requires``; None when unchanged."""
    section = re.search(r'^\[options\][ \t]*\n', text, re.M)
    if section is None:
        return None
    end = re.search(r'^\[', text[section.end():], re.M)
    body_end = section.end() + (end.start() if end else len(text) - section.end())
    body = text[section.end():body_end]
    key = re.search(r'^install_requires[ \t]*=[ \t]*(.*)\n((?:[ \t]+\S.*\n)*)', body, re.M)
    if key is None:
        insert = f'install_requires =\n    {DISTRIBUTION}\n'
        return text[:section.end()] + insert + text[section.end():]
    listed = [key.group(1), *key.group(2).splitlines()]
    if DISTRIBUTION in _names([r for r in listed if r.strip()]):
        return None
    at = section.end() + key.end()
    return f'{text[:at]}    {DISTRIBUTION}\n{text[at:]}'


def add_to_pyproject(text: str) -> str | None:
    """pyproject.toml with RORY in ``[project] dependencies``; None when unchanged (or there
    is no ``[project]`` table: another build tool's file)."""
    try:
        project = tomllib.loads(text).get('project')
    except tomllib.TOMLDecodeError:
        return None
    if not isinstance(project, dict):
        return None
    if DISTRIBUTION in _names([str(d) for d in project.get('dependencies', [])]):
        return None
    section = re.search(r'^\[project\][ \t]*\n', text, re.M)
    if section is None:
        return None
    deps = re.compile(r'^dependencies[ \t]*=[ \t]*\[', re.M).search(text, section.end())
    following = re.compile(r'^\[', re.M).search(text, section.end())
    if deps is not None and (following is None or deps.start() < following.start()):
        return f'{text[:deps.end()]}"{DISTRIBUTION}", {text[deps.end():]}'
    return f'{text[:section.end()]}dependencies = ["{DISTRIBUTION}"]\n{text[section.end():]}'


def declare_runtime(tree: Path) -> tuple[list[str], list[str]]:
    """Add RORY where the package at ``tree``'s top says what it needs.

    Returns:
        The files changed, and warnings (``file: why``) for those left alone.
    """
    changed: list[str] = []
    warnings: list[str] = []
    editors = {
        'package.xml': add_to_package_xml,
        'setup.cfg': add_to_setup_cfg,
        'pyproject.toml': add_to_pyproject,
    }
    for name, edit in editors.items():
        path = tree / name
        if path.is_file():
            new = edit(path.read_text(encoding='utf-8'))
            if new is not None:
                path.write_text(new, encoding='utf-8')
                changed.append(name)
    setup = tree / 'setup.py'
    if setup.is_file():
        new, computed = add_to_setup_py(setup.read_text(encoding='utf-8'))
        if new is not None:
            setup.write_text(new, encoding='utf-8')
            changed.append('setup.py')
        elif computed:
            warnings.append(f'setup.py: install_requires is computed; add {DISTRIBUTION!r} '
                            'to it yourself')
    return changed, warnings
