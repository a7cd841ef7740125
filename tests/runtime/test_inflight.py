"""The in-flight slot survives its writer's death and names the message it was applying."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from rory_runtime.inflight import InFlight, InFlightSlot, read_beat, read_slot


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


def test_heartbeat_is_monotonic_time_and_a_new_process_starts_without_one(
    tmp_path: Path,
) -> None:
    import time

    path = tmp_path / 'slot'
    assert read_beat(path) is None
    slot = InFlightSlot(path, incarnation=1)
    assert read_beat(path) is None  # no beat yet
    before = time.monotonic_ns()
    slot.beat()
    beat = read_beat(path)
    assert beat is not None and before <= beat <= time.monotonic_ns()
    slot.busy('/a' * 200, (1, 2), 3)  # the longest topic does not overwrite the beat
    assert read_beat(path) == beat
    slot.close()
    InFlightSlot(path, incarnation=2).close()
    assert read_beat(path) is None
