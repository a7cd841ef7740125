"""Checkpoints, logs, configs and control messages are data, never code.

Nothing in the runtime or the instrumenter may load with pickle (or its relatives), evaluate
strings, or read YAML with a loader that builds Python objects: a crafted checkpoint or
keyvars.yaml would otherwise run code inside the robot's processes.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ('rory_runtime', 'rory_instrument')
CODE_LOADING_MODULES = {'pickle', 'cPickle', '_pickle', 'marshal', 'shelve', 'dill',
                        'cloudpickle', 'joblib'}
CODE_RUNNING_CALLS = {'eval', 'exec', 'compile', '__import__'}
UNSAFE_YAML = {'load', 'load_all', 'unsafe_load', 'unsafe_load_all', 'full_load',
               'full_load_all'}


# Functions whose job is to run a program, not to read data: the standby runs the node's own
# script as ``python node.py`` would (compile and exec of the file the supervisor config names),
# as runpy did before it (issue 35: runpy put the zygote's __main__ back under the program's
# exit-time checkpoint).
PROGRAM_RUNNERS = {('rory_runtime/standby.py', '_run_file')}


def _sources() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob('*.py'))


def _offences(path: Path, root: Path = ROOT) -> list[str]:
    found = []
    tree = ast.parse(path.read_text(), str(path))
    name = path.relative_to(root).as_posix()
    runners = [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef)
               and (name, n.name) in PROGRAM_RUNNERS]
    allowed = {id(n) for runner in runners for n in ast.walk(runner)}
    for node in ast.walk(tree):
        if id(node) in allowed:
            continue
        if isinstance(node, ast.Import):
            names = [a.name.split('.')[0] for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [(node.module or '').split('.')[0]]
        else:
            names = []
        found += [f'imports {n}' for n in names if n in CODE_LOADING_MODULES]
        if isinstance(node, ast.Call):
            func = node.func
            if isinstance(func, ast.Name) and func.id in CODE_RUNNING_CALLS:
                found.append(f'calls {func.id}()')
            if (isinstance(func, ast.Attribute) and func.attr in UNSAFE_YAML
                    and isinstance(func.value, ast.Name) and func.value.id == 'yaml'):
                found.append(f'calls yaml.{func.attr}()')
    return [f'{path.relative_to(root)}:{o}' for o in found]


def test_the_packages_are_there() -> None:
    assert len(_sources()) > 20


@pytest.mark.parametrize('path', _sources(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_module_loads_or_runs_code_from_data(path: Path) -> None:
    assert _offences(path) == []


def test_the_check_finds_what_it_looks_for(tmp_path: Path) -> None:
    bad = tmp_path / 'bad.py'
    bad.write_text('import pickle\nimport yaml\nx = eval("1")\ny = yaml.load(s)\n')
    offences = [o.split(':', 1)[1] for o in _offences(bad, tmp_path)]
    assert offences == ['imports pickle', 'calls eval()', 'calls yaml.load()']

