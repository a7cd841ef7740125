"""What a robot installs: the runtime alone (no extras) in a clean venv, put to work.

    python -m rory_eval.lean_install [--venv DIR] [--keep]

Makes a new virtual environment, installs this repository into it without extras (``pip
install .``: the instrumenter and the runtime, no MuJoCo, no matplotlib), checks that the
simulator's and the evaluation's packages are absent, then, with that environment's own
``rory-instrument`` and ``rory``, instruments the example integrator, supervises it, SIGKILLs
it while 1..200 arrive and checks that it counted every number once. Prints the installed size
(the venv's site-packages) and its largest distributions. Exit 0 when all of it held.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / 'examples' / 'integrator'
NUMBERS = 200


def _site_packages(venv: Path) -> Path:
    return next((venv / 'lib').glob('python3*/site-packages'))


def _size_mb(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob('*') if f.is_file()) / 1e6


def largest(site: Path, count: int = 6) -> list[tuple[str, float]]:
    """The biggest top-level entries of a site-packages folder, MB."""
    sizes = [(entry.name, _size_mb(entry) if entry.is_dir() else entry.stat().st_size / 1e6)
             for entry in site.iterdir() if not entry.name.endswith('.dist-info')]
    return sorted(sizes, key=lambda item: -item[1])[:count]


def _run(argv: Sequence[str], *, cwd: Path | None = None, env: dict[str, str] | None = None,
         timeout: float | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(list(argv), check=True, capture_output=True, text=True, cwd=cwd,
                          env=env, timeout=timeout)


def crash_and_count(venv: Path, work: Path, domain: int) -> str:
    """Instrument, supervise, kill, tally with the venv's own commands; the tally's line."""
    python, rory = venv / 'bin' / 'python', venv / 'bin' / 'rory'
    shutil.copytree(EXAMPLE, work / 'src')
    _run([str(venv / 'bin' / 'rory-instrument'), 'src', '--vars', 'src/keyvars.yaml', '-o',
          'out'], cwd=work)
    (work / 'supervise.yaml').write_text(
        'nodes:\n  - {name: integrator, command: [python, out/integrator.py]}\n')
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(('ROS_', 'RMW_', 'FAST', 'PYTHONPATH', 'VIRTUAL_ENV'))}
    env.update(ROS_DOMAIN_ID=str(domain), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               PATH=f'{venv / "bin"}{os.pathsep}{env.get("PATH", "")}')
    log = (work / 'supervise.log').open('wb')
    supervisor = subprocess.Popen([str(rory), 'supervise', 'supervise.yaml'], cwd=work, env=env,
                                  stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    publisher = subprocess.Popen([str(python), 'src/count_publisher.py', str(NUMBERS), '50',
                                  '@integrator'], cwd=work, env=env, start_new_session=True)
    try:
        time.sleep(3.0)
        _run([str(rory), 'kill', '.rory', 'integrator'], cwd=work, env=env)
        publisher.wait(timeout=60)
        return _run([str(python), 'src/tally.py', str(NUMBERS)], cwd=work, env=env,
                    timeout=60).stdout.strip()
    finally:
        for proc in (publisher, supervisor):
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT if proc is supervisor else signal.SIGKILL)
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        log.close()


def main(argv: Sequence[str] | None = None) -> int:
    """Install, check, run; 0 when the lean install recovered the integrator exactly."""
    parser = argparse.ArgumentParser(prog='python -m rory_eval.lean_install', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--venv', type=Path, help='where to make it (default: a temp folder)')
    parser.add_argument('--keep', action='store_true', help='leave the venv and the run')
    parser.add_argument('--domain', type=int, default=87)
    args = parser.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix='rory-lean-'))
    venv = (args.venv or root / 'venv').resolve()
    try:
        _run([sys.executable, '-m', 'venv', str(venv)])
        # From a copy: pip builds in the source tree, and the checkout stays as it was.
        source = root / 'source'
        shutil.copytree(REPO, source, ignore=shutil.ignore_patterns(
            '.git', '.venv', 'build', '*.egg-info', '__pycache__', '.*_cache', '*-out'))
        _run([str(venv / 'bin' / 'python'), '-m', 'pip', 'install', '--quiet', str(source)])
        site = _site_packages(venv)
        present = [m for m in ('mujoco', 'matplotlib') if (site / m).exists()]
        if present:
            print(f'lean install: {", ".join(present)} installed without an extra asking')
            return 1
        refused = subprocess.run([str(venv / 'bin' / 'rory'), 'sim', 'list'],
                                 capture_output=True, text=True)
        line = crash_and_count(venv, root / 'run', args.domain)
        size = _size_mb(site)
        print(f'runtime alone: {size:.0f} MB in site-packages; largest: ' + ', '.join(
            f'{name} {mb:.0f} MB' for name, mb in largest(site)))
        print(f'rory sim without the extra: exit {refused.returncode}: {refused.stderr.strip()}')
        print(f'crash and recovery with that install: {line}')
        ok = line.endswith('every number once, none twice') and refused.returncode == 2
        return 0 if ok else 1
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
            if args.venv is not None:
                shutil.rmtree(venv, ignore_errors=True)


if __name__ == '__main__':
    sys.exit(main())
