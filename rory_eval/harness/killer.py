"""The SIGKILL of a crash run: the supervised node, a set time after the simulator's clock starts.

The evaluation's runs (rory_eval/runs/runner.py), the exact-output check
(rory_eval/faults/target_crash.py) and the fleet (rory_eval/harness/fleet.py) crash their node
with it. The node's pid is the supervisor's last ``spawn`` event in the store.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

from rory_eval.harness.simrun import store_events, wait_for_clock

KILL_TIMEOUT = 120.0  # s to wait for the clock before giving up on the kill


class Killer(threading.Thread):
    """SIGKILLs the supervised node ``crash_at`` seconds after the simulator's clock starts."""

    def __init__(self, sim_log: Path, world: str, store: Path, crash_at: float) -> None:
        super().__init__(daemon=True, name='killer')
        self.sim_log, self.world, self.store, self.crash_at = sim_log, world, store, crash_at
        self.killed_at: float | None = None
        self.error = ''
        self._finish = threading.Event()

    def run(self) -> None:
        if not wait_for_clock(self.sim_log, self.world, self._finish, KILL_TIMEOUT):
            self.error = 'the clock never started'
            return
        clock_start = time.monotonic()
        if self._finish.wait(self.crash_at):
            self.error = 'the run ended before the crash time'
            return
        spawns = [e for e in store_events(self.store) if e.get('kind') == 'spawn']
        if not spawns:
            self.error = 'the supervisor never started the node'
            return
        try:
            os.kill(int(spawns[-1]['pid']), signal.SIGKILL)
        except ProcessLookupError:
            self.error = f'node pid {spawns[-1]["pid"]} was already gone'
            return
        self.killed_at = time.monotonic() - clock_start

    def stop(self) -> None:
        self._finish.set()
        self.join(timeout=2.0)
