"""The crash runs' SIGKILL (rory_eval/harness/killer.py), with a sleeping process as the node."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from rory_eval.harness.killer import Killer


def _started(folder: Path, world: str) -> Path:
    """A simulator log that says the clock runs."""
    log = folder / 'sim.log'
    log.write_text(f'{world}: running (seed 0)\n')
    return log


def test_the_last_spawned_node_is_killed_after_the_crash_time(tmp_path: Path) -> None:
    node = subprocess.Popen(['sleep', '30'])
    try:
        store = tmp_path / 'store'
        store.mkdir()
        (store / 'events.jsonl').write_text(
            json.dumps({'kind': 'spawn', 'pid': 1}) + '\n'
            + json.dumps({'kind': 'spawn', 'pid': node.pid}) + '\n')
        killer = Killer(_started(tmp_path, 'office_small'), 'office_small', store, 0.1)
        killer.start()
        assert node.wait(timeout=10) == -9
        killer.join(timeout=5)
        assert killer.error == '' and killer.killed_at is not None and killer.killed_at >= 0.1
    finally:
        node.kill()
        node.wait()


def test_no_spawn_and_an_early_stop_are_errors_not_kills(tmp_path: Path) -> None:
    log = _started(tmp_path, 'workshop')
    killer = Killer(log, 'workshop', tmp_path / 'store', 0.0)
    killer.start()
    killer.join(timeout=5)
    assert killer.error == 'the supervisor never started the node' and killer.killed_at is None
    early = Killer(log, 'workshop', tmp_path / 'store', 30.0)
    early.start()
    early.stop()
    assert early.error == 'the run ended before the crash time' and early.killed_at is None
