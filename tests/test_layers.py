"""The layers of docs/architecture.md ("Module map"), held: who may import whom.

Every import statement is read from the source (also those inside functions, which load
lazily but load all the same), relative imports resolved to the package they name.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix('').parts)
    if parts[-1] == '__init__':
        parts.pop()
    return '.'.join(parts)


def imports(path: Path, module: str | None = None) -> Iterator[str]:
    """Every module ``path`` (the module ``module``, by default its name under ROOT) imports,
    absolute."""
    tree = ast.parse(path.read_text(), str(path))
    package = (module or module_name(path)).split('.')
    if path.name != '__init__.py':
        package.pop()
    for node in ast.walk(tree):
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
    node_side = [p for p in (ROOT / 'rory_runtime').glob('*.py')
                 if p.stem not in NODE_SIDE_EXCEPT]
    assert len(node_side) > 15
    # rory_runtime.supervise() runs a supervisor from a program: loaded when it is called.
    assert violations(node_side, ('rory_runtime.supervisor',),
                      {'rory_runtime': ('rory_runtime.supervisor.embed',)}) == []


SUPERVISOR_DECISIONS = ('states', 'watchdog', 'events', 'output', 'lineage', 'ports', 'recovery',
                        'poison', 'run_marker', 'config', 'process')
"""The supervisor's modules that decide and keep records; rclpy is reached through the ports
(supervisor/ports.py), so their unit tests run on fakes."""


@pytest.mark.parametrize('name', SUPERVISOR_DECISIONS)
def test_the_supervisors_decisions_import_no_rclpy(name: str) -> None:
    path = ROOT / 'rory_runtime' / 'supervisor' / f'{name}.py'
    assert violations([path], ('rclpy',)) == []


def test_the_evaluations_harness_is_its_bottom_layer() -> None:
    lower = [*sources('rory_eval/harness'), ROOT / 'rory_eval' / 'targets.py',
             ROOT / 'rory_eval' / 'metrics.py']
    upper = tuple(f'rory_eval.{p}' for p in ('bench', 'faults', 'demos', 'evaluation',
                                             'quality'))
    assert violations(lower, upper) == []


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
