"""A harness killed with SIGTERM still runs its ``finally`` blocks (and so reaps its runs)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

PROGRAM = """
import sys, time
from pathlib import Path
from rory_eval.harness.simrun import exit_on_sigterm
exit_on_sigterm()
marker = Path(sys.argv[1])
try:
    marker.write_text('running')
    time.sleep(60)
finally:
    marker.write_text('reaped')
"""


def test_sigterm_runs_the_finally_blocks(tmp_path: Path) -> None:
    marker = tmp_path / 'marker'
    proc = subprocess.Popen([sys.executable, '-c', PROGRAM, str(marker)])
    try:
        deadline = time.monotonic() + 30
        while not (marker.exists() and marker.read_text() == 'running'):
            assert time.monotonic() < deadline, 'the program never started'
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 128 + signal.SIGTERM
    finally:
        proc.kill()
        proc.wait()
    assert marker.read_text() == 'reaped'
