"""README's tour, step 4, run as written for every method at once (each in its own folder and
ROS domain): instrument, supervise, crash with `rory kill`, tally, stop cleanly. The tally's
line is the one README's table gives for the method; under rory the checkpoint taken at the
clean stop holds the whole count."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
from collections.abc import Callable
from pathlib import Path

import pytest

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[2]
METHODS = ('rory', 'replay', 'checkpoint', 'restart')


def _tour_step() -> str:
    readme = (REPO / 'README.md').read_text()
    step = readme.index('4. **Crash it.**')
    return readme[step:readme.index('\n## ', step)]


def _tour_script() -> str:
    block = re.search(r'```sh\n(.*?)```', _tour_step(), re.S)
    assert block is not None, 'no shell block in the tour step 4'
    return '\n'.join(line.removeprefix('   ') for line in block.group(1).splitlines())


def _tally_lines() -> dict[str, str]:
    """README's table: method -> the tally's line."""
    lines = {}
    for row in re.finditer(r'^   \| (.+?) \| `(integrator: .+?)` \|$', _tour_step(), re.M):
        for method in re.findall(r'`(\w+)`', row.group(1)):
            lines[method] = row.group(2)
    return lines


def _start(folder: Path, method: str, domain: int) -> subprocess.Popen[str]:
    folder.mkdir()
    shutil.copytree(REPO / 'examples', folder / 'examples')
    (folder / '.venv').symlink_to(REPO / '.venv')
    script = _tour_script()
    assert 'method=rory ' in script
    script = script.replace('method=rory ', f'method={method} ', 1)
    (folder / 'tour.sh').write_text(f'export ROS_DOMAIN_ID={domain}\n{script}\n')
    return subprocess.Popen(['bash', 'tour.sh'], cwd=folder, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env={k: v for k, v in os.environ.items()
                                 if not k.startswith(('ROS_', 'RMW_', 'FAST'))})


def _finish(proc: subprocess.Popen[str]) -> str:
    try:
        out, _ = proc.communicate(timeout=150)
    finally:
        with contextlib.suppress(ProcessLookupError):  # its background jobs, should one linger
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    return out


def test_the_tour_prints_each_methods_line(
    tmp_path: Path, ros_domain: int, more_ros_domains: Callable[[], int]
) -> None:
    expected = _tally_lines()
    assert sorted(expected) == sorted(METHODS), expected
    domains = [ros_domain, *(more_ros_domains() for _ in METHODS[1:])]
    procs = {m: _start(tmp_path / m, m, d) for m, d in zip(METHODS, domains, strict=True)}
    outs = {m: _finish(p) for m, p in procs.items()}
    for method, out in outs.items():
        assert 'sent SIGKILL to integrator' in out, (method, out)
        assert 'RUNNING -> CRASHED (killed by SIGKILL)' in out, (method, out)
        tallies = [line for line in out.splitlines() if line.startswith('integrator: ')]
        assert tallies == [expected[method]], (method, out[-3000:])
    inspected = subprocess.run(
        [str(REPO / '.venv/bin/rory'), 'inspect', str(tmp_path / 'rory/tour/.rory'), '--node',
         'integrator', '--checkpoint', 'latest'], capture_output=True, text=True, check=True)
    assert '  total = 180300\n' in inspected.stdout and '  count = 600\n' in inspected.stdout
