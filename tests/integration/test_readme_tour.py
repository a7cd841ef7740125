"""README's tour, step 4, run as written: instrument, supervise, crash with `rory kill`, stop
cleanly, inspect. The printed values are the same every run: nothing lost, nothing twice."""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[2]


def _tour_script() -> str:
    readme = (REPO / 'README.md').read_text()
    step = readme[readme.index('4. **Crash it.**'):]
    block = re.search(r'```sh\n(.*?)```', step, re.S)
    assert block is not None, 'no shell block in the tour step 4'
    return '\n'.join(line.removeprefix('   ') for line in block.group(1).splitlines())


def test_the_tour_prints_the_whole_count(tmp_path: Path, ros_domain: int) -> None:
    shutil.copytree(REPO / 'examples', tmp_path / 'examples')
    (tmp_path / '.venv').symlink_to(REPO / '.venv')
    script = tmp_path / 'tour.sh'
    script.write_text(f'export ROS_DOMAIN_ID={ros_domain}\n{_tour_script()}\n')
    proc = subprocess.Popen(['bash', str(script)], cwd=tmp_path, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env={k: v for k, v in os.environ.items()
                                 if not k.startswith(('ROS_', 'RMW_', 'FAST'))})
    try:
        out, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        else:  # the script's background jobs, should one outlive it
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
    assert 'sent SIGKILL to integrator' in out, out
    assert 'RUNNING -> CRASHED (killed by SIGKILL)' in out, out
    assert out.endswith('  total = 180300\n  count = 600\n'), out[-2000:]
