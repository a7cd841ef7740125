"""The in-flight slot survives its writer's death and names the message it was applying."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from rory_runtime.inflight import InFlight, InFlightSlot, read_slot


def test_busy_then_idle(tmp_path: Path) -> None:
    slot = InFlightSlot(tmp_path / 'n' / 'inflight', incarnation=3)
    slot.busy('/numbers', (123, 7), 456)
    assert read_slot(tmp_path / 'n' / 'inflight') == InFlight(3, '/numbers', (123, 7), 456)
    slot.idle()
    assert read_slot(tmp_path / 'n' / 'inflight') is None
    slot.close()
    assert (tmp_path / 'n' / 'inflight').stat().st_mode & 0o777 == 0o600


def test_a_killed_writer_leaves_the_message_it_was_applying(tmp_path: Path) -> None:
    path = tmp_path / 'inflight'
    code = (
        'import os, signal\n'
        'from pathlib import Path\n'
        'from rory_runtime.inflight import InFlightSlot\n'
        f'slot = InFlightSlot(Path({str(path)!r}), incarnation=2)\n'
        "slot.busy('/scan', (99, 4), 5)\n"
        'os.kill(os.getpid(), signal.SIGKILL)\n'
    )
    proc = subprocess.run([sys.executable, '-c', code], check=False)
    assert proc.returncode == -signal.SIGKILL
    assert read_slot(path) == InFlight(2, '/scan', (99, 4), 5)


def test_garbage_or_missing_slot_reads_as_nothing(tmp_path: Path) -> None:
    assert read_slot(tmp_path / 'absent') is None
    (tmp_path / 'garbage').write_bytes(os.urandom(256))
    assert read_slot(tmp_path / 'garbage') is None
    (tmp_path / 'short').write_bytes(b'RYIF')
    assert read_slot(tmp_path / 'short') is None
