"""The installed ``rory-instrument`` command and ``python -m rory_instrument``, as subprocesses."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

INTEGRATOR_SOURCE = '''\
import rclpy
from rclpy.node import Node
from std_msgs.msg import Int64


class Integrator(Node):
    """Sums numbers."""

    def __init__(self):
        super().__init__('integrator')
        self.total = 0  # running sum
        self.count = 0
        self.history = []
'''

KEYVARS = '''\
nodes:
  - file: integrator.py      # relative to SRC
    class: Integrator
    vars: [total, count, history]
'''

COMMAND = Path(sys.executable).parent / 'rory-instrument'


def tree(root: Path) -> dict[str, tuple[str, bytes | str]]:
    """Maps each path below ``root`` to its kind, mode and content (or link target)."""
    entries: dict[str, tuple[str, bytes | str]] = {}
    for path in sorted(root.rglob('*')):
        rel = path.relative_to(root).as_posix()
        mode = oct(stat.S_IMODE(path.lstat().st_mode))
        if path.is_symlink():
            entries[rel] = (f'link {mode}', os.readlink(path))
        elif path.is_dir():
            entries[rel] = (f'dir {mode}', b'')
        else:
            entries[rel] = (f'file {mode}', path.read_bytes())
    return entries


@pytest.fixture
def src(tmp_path: Path) -> Path:
    """A package tree with a node, a binary file, an executable and a symlink."""
    root = tmp_path / 'src'
    (root / 'launch').mkdir(parents=True)
    (root / 'data').mkdir()
    (root / 'integrator.py').write_text(INTEGRATOR_SOURCE)
    (root / 'data' / 'weights.bin').write_bytes(bytes(range(256)) * 4 + b'\r\n\x00')
    script = root / 'launch' / 'run.sh'
    script.write_text('#!/bin/sh\nexec python3 -m integrator\n')
    script.chmod(0o755)
    (root / 'launch' / 'readonly.txt').write_text('do not touch\n')
    (root / 'launch' / 'readonly.txt').chmod(0o444)
    (root / 'README.md').write_text('# Integrator\n\nNo trailing newline')
    (root / 'link.py').symlink_to('integrator.py')
    (tmp_path / 'keyvars.yaml').write_text(KEYVARS)
    return root


def run(*argv: str | Path, cwd: Path, module: bool = False) -> subprocess.CompletedProcess[str]:
    head = [sys.executable, '-m', 'rory_instrument'] if module else [str(COMMAND)]
    return subprocess.run([*head, *map(str, argv)], cwd=cwd, capture_output=True, text=True,
                          timeout=120, check=False)


def test_copies_everything_else_byte_for_byte(src: Path) -> None:
    work = src.parent
    done = run('src', '--vars', 'keyvars.yaml', '-o', 'out', cwd=work)
    assert (done.returncode, done.stderr) == (0, '')
    assert done.stdout == 'instrumented integrator.py:Integrator vars=total,count,history\n'
    before, after = tree(src), tree(work / 'out')
    assert set(after) == set(before) | {'rory_manifest.json'}
    changed = {rel for rel in before if before[rel] != after[rel]}
    assert changed == {'integrator.py'}
    # The instrumented file keeps its mode; only its content changed.
    assert before['integrator.py'][0] == after['integrator.py'][0]
    text = (work / 'out' / 'integrator.py').read_text()
    assert text.startswith(
        'import rclpy\nfrom rclpy.node import Node\nfrom std_msgs.msg import Int64\n'
        'import rory_runtime\n\n\n@rory_runtime.checkpointed(vars=("total", "count", '
        '"history"), manifest="sha256:'
    )
    assert text.endswith('")\n' + INTEGRATOR_SOURCE[INTEGRATOR_SOURCE.index('class '):])


def test_a_relative_link_to_a_file_outside_src_is_copied_as_that_file(src: Path) -> None:
    # Copied as a link, ../shared/geometry.py would point at nothing next to OUT.
    work = src.parent
    (work / 'shared').mkdir()
    (work / 'shared' / 'geometry.py').write_text('def wrap(a: float) -> float:\n    return a\n')
    (work / 'shared' / 'data').mkdir()
    (src / 'geometry.py').symlink_to('../shared/geometry.py')
    (src / 'data_dir').symlink_to('../shared/data', target_is_directory=True)
    (src / 'absolute.py').symlink_to(work / 'shared' / 'geometry.py')
    (src / 'dangling.py').symlink_to('../shared/missing.py')
    done = run('src', '--vars', 'keyvars.yaml', '-o', 'out', cwd=work)
    assert (done.returncode, done.stderr) == (0, '')
    before, after = tree(src), tree(work / 'out')
    shared = work / 'shared' / 'geometry.py'
    mode = oct(stat.S_IMODE(shared.stat().st_mode))
    assert after['geometry.py'] == (f'file {mode}', shared.read_bytes())
    # Links inside SRC, absolute links, links to directories and dangling links stay links.
    for rel in ('link.py', 'data_dir', 'absolute.py', 'dangling.py'):
        assert after[rel] == before[rel]
        assert after[rel][0].startswith('link ')
    assert set(after) == set(before) | {'rory_manifest.json'}
    again = run('out', '--vars', 'keyvars.yaml', '-o', 'out2', cwd=work)
    assert (again.returncode, again.stderr) == (0, '')
    assert tree(work / 'out2') == tree(work / 'out')


def test_rerun_on_output_gives_identical_tree(src: Path) -> None:
    work = src.parent
    assert run('src', '--vars', 'keyvars.yaml', '-o', 'out', cwd=work).returncode == 0
    again = run('out', '--vars', 'keyvars.yaml', '-o', 'out2', cwd=work, module=True)
    assert (again.returncode, again.stderr) == (0, '')
    assert tree(work / 'out2') == tree(work / 'out')


def test_rerun_replaces_previous_output(src: Path) -> None:
    work = src.parent
    assert run('src', '--vars', 'keyvars.yaml', '-o', 'out', cwd=work).returncode == 0
    first = tree(work / 'out')
    (src / 'added.txt').write_text('new\n')
    assert run(src, '--vars', work / 'keyvars.yaml', '-o', work / 'out', cwd=src).returncode == 0
    second = tree(work / 'out')
    assert set(second) == set(first) | {'added.txt'}
    assert sorted(p.name for p in work.iterdir()) == ['keyvars.yaml', 'out', 'src']


def test_input_error_exit_code_and_message(src: Path) -> None:
    work = src.parent
    (work / 'keyvars.yaml').write_text(KEYVARS.replace('history]', 'histroy]'))
    done = run('src', '--vars', 'keyvars.yaml', '-o', 'out', cwd=work)
    assert done.returncode == 2
    assert done.stdout == ''
    assert done.stderr == (
        'src/integrator.py:6:1: Integrator never assigns self.histroy '
        '(vars: total, count, histroy)\n'
    )
    assert not (work / 'out').exists()


@pytest.mark.parametrize(
    'argv',
    [
        ['src', '--vars', 'missing.yaml', '-o', 'out'],
        ['missing', '--vars', 'keyvars.yaml', '-o', 'out'],
        ['src', '-o', 'out'],
        ['src', '--vars', 'keyvars.yaml'],
    ],
)
def test_bad_arguments_exit_2_without_traceback(src: Path, argv: list[str]) -> None:
    done = run(*argv, cwd=src.parent)
    assert done.returncode == 2
    assert 'Traceback' not in done.stderr
    assert done.stderr.strip()
    assert not (src.parent / 'out').exists()


def test_help(src: Path) -> None:
    done = run('--help', cwd=src.parent, module=True)
    assert done.returncode == 0
    assert '--vars' in done.stdout and '--check' in done.stdout


def test_a_direct_clock_read_is_warned_on_stderr_and_the_tree_is_still_written(
    src: Path,
) -> None:
    source = src / 'integrator.py'
    source.write_text(INTEGRATOR_SOURCE.replace(
        'import rclpy\n', 'import time\n\nimport rclpy\n'
    ) + '        self.started = time.time()\n')
    done = run('src', '--vars', 'keyvars.yaml', '-o', 'out', cwd=src.parent)
    assert done.returncode == 0
    assert done.stderr == (
        'src/integrator.py:16:24: warning: time.time() is read directly; RORY cannot replay '
        'it after a crash (in a callback, read self.get_clock().now())\n')
    assert (src.parent / 'out' / 'integrator.py').exists()
