"""The layers of docs/architecture.md ("Module map"), held: who may import whom.

Every import statement is read from the source (also those inside functions, which load
lazily but load all the same), relative imports resolved to the package they name. The
supervisor's decision modules are followed further, through what the modules they reach load
(``rclpy_paths``); the evaluation's layers are also the order of the module map's last rows.
"""

from __future__ import annotations

import ast
import re
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


FUNCTIONS = (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)


def _statements(tree: ast.AST, at_load: bool) -> Iterator[ast.AST]:
    """Every node of ``tree``; ``at_load``: only those that run when the module is loaded (not
    the bodies of its functions)."""
    stack = [tree]
    while stack:
        node = stack.pop()
        yield node
        stack.extend(child for child in ast.iter_child_nodes(node)
                     if not (at_load and isinstance(child, FUNCTIONS)))


def imports(path: Path, module: str | None = None, *, at_load: bool = False) -> Iterator[str]:
    """Every module ``path`` (the module ``module``, by default its name under ROOT) imports,
    absolute; ``at_load``: only the imports that run when it is loaded (also those under ``if
    TYPE_CHECKING:``, which mypy loads), not those inside its functions."""
    tree = ast.parse(path.read_text(), str(path))
    package = (module or module_name(path)).split('.')
    if path.name != '__init__.py':
        package.pop()
    for node in _statements(tree, at_load):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                target = '.'.join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ''
            yield target
            # `from . import protocol` imports a module too
            yield from (f'{target}.{alias.name}' for alias in node.names)


def sources(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob('*.py'))


def modules(folder: str) -> dict[str, Path]:
    """The modules under ``folder`` by name (a package by its ``__init__.py``)."""
    return {module_name(path): path for path in sources(folder)}


def ours(name: str, known: dict[str, Path]) -> str | None:
    """The module of ``known`` that the imported ``name`` loads (``a.b.C`` is ``a.b``'s), if
    any."""
    while name and name not in known:
        name = name.rpartition('.')[0]
    return name or None


def module_graph(folder: str) -> dict[str, set[str]]:
    """Module -> the modules of the same folder it imports."""
    known = modules(folder)
    return {name: {target for imported in imports(path)
                   if (target := ours(imported, known)) not in (None, name)}
            for name, path in known.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return sorted(found)


def violations(paths: list[Path], forbidden: tuple[str, ...],
               allowed: dict[str, tuple[str, ...]] | None = None) -> list[str]:
    found = []
    for path in paths:
        exempt = (allowed or {}).get(module_name(path), ())
        for name in imports(path):
            hit = any(name == f or name.startswith(f + '.') for f in forbidden)
            if hit and not any(name == e or name.startswith(e + '.') for e in exempt):
                found.append(f'{path.relative_to(ROOT)} imports {name}')
    return sorted(set(found))


def test_the_runtime_imports_no_evaluation_simulator_or_instrumenter() -> None:
    # `rory sim` and `rory eval` run the simulator and the evaluation (extras) as programs.
    assert violations(sources('rory_runtime'),
                      ('rory_eval', 'sim', 'targets', 'rory_instrument')) == []


def test_the_instrumenter_stands_alone() -> None:
    # It writes code that imports rory_runtime; it does not import it.
    assert violations(sources('rory_instrument'), ('rory_runtime', 'rory_eval', 'sim')) == []


NODE_SIDE_EXCEPT = {'cli', 'bundle', 'kill', 'inspection'}
"""rory_runtime's top-level modules a node process never loads: commands an operator runs."""


def test_what_a_node_process_loads_never_imports_the_supervisor() -> None:
    # The node side (rory_runtime/node/) and what it stands on (rory_runtime's top level).
    node_side = [p for p in (ROOT / 'rory_runtime').glob('*.py')
                 if p.stem not in NODE_SIDE_EXCEPT]
    node_side += sorted((ROOT / 'rory_runtime' / 'node').glob('*.py'))
    assert len(node_side) > 15
    # rory_runtime.supervise() runs a supervisor from a program: loaded when it is called.
    assert violations(node_side, ('rory_runtime.supervisor',),
                      {'rory_runtime': ('rory_runtime.supervisor.embed',)}) == []


def test_the_node_side_and_the_supervisor_import_neither_the_other() -> None:
    # The runtime's two sides (docs/architecture.md, "Module map"): what runs in a node's process
    # (rory_runtime/node/) and the supervisor (rory_runtime/supervisor/) meet only on what both
    # stand on, rory_runtime's top level. The zygote loads the node side for the nodes it forks
    # by name (supervisor.py: preload), not by an import.
    node = sources('rory_runtime/node')
    supervisor = sources('rory_runtime/supervisor')
    assert len(node) > 10 and len(supervisor) > 20
    assert violations(supervisor, ('rory_runtime.node',)) == []
    assert violations(node, ('rory_runtime.supervisor',)) == []


SUPERVISOR_DECISIONS = ('states', 'watchdog', 'events', 'output', 'lineage', 'ports', 'recovery',
                        'poison', 'run_marker', 'config', 'process', 'managed_node', 'gate',
                        'loop_events', 'health', 'standby_keeper', 'incarnation', 'handover',
                        'readers', 'recoveries')
"""The supervisor's modules that decide and keep records; rclpy is reached through the ports
(supervisor/ports.py), so their unit tests run on fakes. ManagedNode's own module is one: the
ROS side (supervisor.py) makes the readers, writers and services behind its ports."""


@pytest.mark.parametrize('name', SUPERVISOR_DECISIONS)
def test_the_supervisors_decisions_import_no_rclpy(name: str) -> None:
    path = ROOT / 'rory_runtime' / 'supervisor' / f'{name}.py'
    assert violations([path], ('rclpy',)) == []


KNOWN_RCLPY_CARRIERS: dict[str, str] = {}
# (Empty since ports.RingPort replaced the concrete Ring in ports and recovery, issue 39.)
"""rory_runtime's modules through which a decision module loads rclpy today, with why: the
test below does not look past them (it still looks at everything else the decisions load), and
fails once one of them is no longer needed, so that the exception goes."""


def _under(name: str, prefixes: Iterable[str]) -> bool:
    return any(name == p or name.startswith(p + '.') for p in prefixes)


def rclpy_paths(start: str, carriers: Iterable[str] | None = None) -> list[str]:
    """How loading rory_runtime's module ``start`` and calling its functions loads rclpy,
    through rory_runtime's own modules: each chain ``start -> ... -> rclpy...``, not looking
    past the ``carriers`` (by default the known ones).

    ``start``'s imports are all read (also inside its functions); of every module it then
    loads, what runs when that is loaded (its imports outside functions), and its packages'
    ``__init__.py``, which Python loads first."""
    stop = tuple(KNOWN_RCLPY_CARRIERS if carriers is None else carriers)
    known = modules('rory_runtime')
    chains: list[str] = []
    came_from: dict[str, str | None] = {start: None}
    queue = [start]
    while queue:
        here = queue.pop(0)
        route = [here]
        while (back := came_from[route[-1]]) is not None:
            route.append(back)
        route.reverse()
        parts = here.split('.')
        parents = ['.'.join(parts[:i]) for i in range(1, len(parts))]
        for name in [*imports(known[here], here, at_load=here != start), *parents]:
            if _under(name, ('rclpy',)):
                chains.append(' -> '.join([*route, name]))
            elif ((target := ours(name, known)) is not None and target not in came_from
                  and not _under(target, stop)):
                came_from[target] = here
                queue.append(target)
    return sorted(set(chains))


@pytest.mark.parametrize('name', SUPERVISOR_DECISIONS)
def test_the_supervisors_decisions_load_no_rclpy_through_other_modules(name: str) -> None:
    assert rclpy_paths(f'rory_runtime.supervisor.{name}') == []


def test_each_known_rclpy_carrier_is_still_needed() -> None:
    for carrier in KNOWN_RCLPY_CARRIERS:
        others = [c for c in KNOWN_RCLPY_CARRIERS if c != carrier]
        through = [chain for name in SUPERVISOR_DECISIONS
                   for chain in rclpy_paths(f'rory_runtime.supervisor.{name}', others)
                   if any(_under(step, (carrier,)) for step in chain.split(' -> '))]
        assert through, f'no decision module loads rclpy through {carrier} any more: drop it'


def test_the_rclpy_paths_follow_packages_and_load_time_imports(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch,
                                                               ) -> None:
    root = tmp_path / 'rory_runtime'
    (root / 'supervisor').mkdir(parents=True)
    (root / '__init__.py').write_text('from .base import X\n\ndef later():\n    import rclpy\n')
    (root / 'base.py').write_text('import rclpy.qos\n')
    (root / 'supervisor' / '__init__.py').write_text('')
    (root / 'supervisor' / 'decide.py').write_text(
        'from .helper import f\n\ndef g():\n    from .. import tool\n')
    (root / 'supervisor' / 'helper.py').write_text('def f():\n    import rclpy.node\n')
    (root / 'tool.py').write_text('from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n'
                                  '    from rclpy.node import Node\n')
    monkeypatch.setattr(sys.modules[__name__], 'ROOT', tmp_path)
    monkeypatch.setattr(sys.modules[__name__], 'KNOWN_RCLPY_CARRIERS', {})
    assert rclpy_paths('rory_runtime.supervisor.decide') == [
        'rory_runtime.supervisor.decide -> rory_runtime -> rory_runtime.base -> rclpy.qos',
        'rory_runtime.supervisor.decide -> rory_runtime.tool -> rclpy.node',
        'rory_runtime.supervisor.decide -> rory_runtime.tool -> rclpy.node.Node',
    ]


EVAL_LAYERS = (
    ('targets', 'metrics', 'lean_install'),
    ('harness',),
    ('quality',),
    ('runs',),
    ('bench', 'faults'),
    ('evaluation',),
    ('demos',),
)
"""rory_eval's modules and packages, bottom first, as the module map's last rows list them: each
imports only from itself and the rows before its own; two sharing a row import neither
the other."""


def eval_part(name: str) -> str | None:
    """The entry of :data:`EVAL_LAYERS` an imported ``rory_eval...`` name belongs to."""
    parts = name.split('.')
    return parts[1] if len(parts) > 1 and parts[0] == 'rory_eval' else None


def test_every_part_of_the_evaluation_has_a_layer() -> None:
    here = ROOT / 'rory_eval'
    parts = {p.stem for p in here.glob('*.py') if p.stem != '__init__'}
    parts |= {p.name for p in here.iterdir() if (p / '__init__.py').exists()}
    assert parts == {part for row in EVAL_LAYERS for part in row}


def test_the_evaluation_imports_only_downward() -> None:
    layer = {part: i for i, row in enumerate(EVAL_LAYERS) for part in row}
    found = []
    for path in sources('rory_eval'):
        mine = eval_part(module_name(path))
        for name in imports(path):
            theirs = eval_part(name)
            if mine is None or theirs is None or theirs == mine:
                continue
            if theirs not in layer or layer[theirs] >= layer[mine]:
                found.append(f'{path.relative_to(ROOT)} ({mine}) imports {name}')
    assert sorted(set(found)) == []


def module_map_rows() -> list[list[str]]:
    """The cells of each row of docs/architecture.md's module map, top to bottom."""
    text = (ROOT / 'docs' / 'architecture.md').read_text()
    section = text.split('\n## Module map\n', 1)[1].split('\n## ', 1)[0]
    rows = [line for line in section.splitlines() if line.startswith('|')]
    assert rows[0].startswith('| layer |') and set(rows[1]) <= set('|-')
    return [[cell.strip() for cell in row.strip('|').split(' | ')] for row in rows[2:]]


def test_the_module_maps_last_rows_are_the_evaluations_layers_in_order() -> None:
    # A row imports from the rows above it; rory_eval stands on all the others.
    named = [set(re.findall(r'`rory_eval/(\w+)(?:/|\.py)`', cells[1]))
             for cells in module_map_rows()]
    assert named[-len(EVAL_LAYERS):] == [set(row) for row in EVAL_LAYERS]
    assert not any(named[:-len(EVAL_LAYERS)])


@pytest.mark.parametrize('folder', ['sim', 'rory_eval'])
def test_no_import_cycle_between_modules(folder: str) -> None:
    assert cycles(module_graph(folder)) == []


def test_cycles_are_found() -> None:
    graph = {'a': {'b'}, 'b': {'c'}, 'c': {'a'}, 'd': {'a', 'e'}, 'e': {'d'}, 'f': set()}
    assert cycles(graph) == [['a', 'b', 'c'], ['d', 'e']]


@pytest.mark.parametrize('folder', ['sim', 'targets'])
def test_the_simulator_and_targets_are_plain_ros_programs(folder: str) -> None:
    assert violations(sources(folder), ('rory_runtime', 'rory_eval', 'rory_instrument')) == []


def test_imports_inside_functions_and_relative_ones_are_resolved(tmp_path: Path) -> None:
    probe = tmp_path / 'probe.py'
    probe.write_text('import os\n\ndef f():\n    from .supervisor import states\n'
                     '    from ..sim import x\n')
    assert sorted(imports(probe, 'rory_runtime.probe')) == [
        'os', 'rory_runtime.supervisor', 'rory_runtime.supervisor.states', 'sim', 'sim.x']
    init = tmp_path / '__init__.py'
    init.write_text('from .supervisor.embed import supervise\n')
    assert sorted(imports(init, 'rory_runtime')) == [
        'rory_runtime.supervisor.embed', 'rory_runtime.supervisor.embed.supervise']
