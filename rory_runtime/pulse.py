"""RORY's side thread in a node: the heartbeat and the checkpoint schedule, with nothing of
RORY's in the node's executor (docs/architecture.md, "Heartbeat" and "Nothing in the node's
executor").

rclpy's executor pays for every entity of a node at every callback (docs/performance.md, "Nothing
of RORY's in the node's executor"), so RORY keeps no timer of its own there. One daemon thread
wakes every :data:`BEAT_PERIOD` and

* **beats** for the executor: when a callback RORY runs (a message, a tick, a request, a
  parameter change) finished since its last look, the executor is alive and the thread writes
  the beat itself; when none did, it posts a *probe* with ``Executor.create_task`` (thread-safe;
  it wakes the executor through the executor's own guard condition, no entity added) and the
  probe writes the beat when the executor runs it. A callback that never returns, a deadlock or
  a busy loop leaves the probe waiting and the beat stops, as the timer's did; a node busy with
  its inputs is never woken for it, and an idle one is woken as often as the timer woke it.
* **schedules checkpoints** on the node's own clock (ROS time: simulation time when the node
  uses it, so a /clock that stands still takes none, as a timer would not fire): when one is
  due it posts the checkpoint (or, for the replay method, the log rotation) to the executor the
  same way, one at a time.

:class:`Pulse` is driven by :meth:`Pulse.tick`, which the thread calls; tests call it with fakes
for the executor and the clocks (tests/runtime/test_pulse.py).
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

_logger = logging.getLogger('rory.pulse')

BEAT_PERIOD = 0.2
"""Seconds between the thread's looks (the supervisor's hang_timeout is far longer; a beat 3
periods late already makes it keep the node's inputs: supervisor/watchdog.py)."""


class TaskRunner(Protocol):
    """What the pulse needs of rclpy's ``Executor``."""

    def create_task(self, callback: Callable[[], None]) -> object:
        """Run ``callback`` on the executor's thread at its next wake-up (thread-safe)."""
        ...


@dataclass
class CheckpointSchedule:
    """When the next checkpoint is due on the node's clock, every ``interval_ns`` from the first.

    Like an rcl timer it keeps its grid: a late run does not move the next due time, and due
    times missed together (a clock that jumped ahead, a long callback) are run once.
    """

    interval_ns: int
    next_ns: int

    def due(self, now_ns: int) -> bool:
        """Whether one is due at ``now_ns``; if so, the next due time moves on past it."""
        if now_ns < self.next_ns:
            if self.next_ns - now_ns > self.interval_ns:
                # The clock went back (a simulation restarted): start again from it.
                self.next_ns = now_ns + self.interval_ns
            return False
        missed = (now_ns - self.next_ns) // self.interval_ns
        self.next_ns += (missed + 1) * self.interval_ns
        return True


class Pulse:
    """The heartbeat and the checkpoint schedule of one node, posted to its executor.

    Args:
        executor: The node's executor now (``Node.executor``), None before it spins.
        beat: Writes the heartbeat (the in-flight slot's).
        progress: A count of the callbacks RORY has run to their end, read without the lock.
        node_now_ns: The node's own clock, read live (for the checkpoint schedule).
    """

    def __init__(self, executor: Callable[[], TaskRunner | None], beat: Callable[[], None],
                 progress: Callable[[], int], node_now_ns: Callable[[], int]) -> None:
        self._executor = executor
        self._beat = beat
        self._progress = progress
        self._node_now_ns = node_now_ns
        self._seen_progress = -1
        self._probe_waiting = False
        self._checkpoint: tuple[CheckpointSchedule, Callable[[], None]] | None = None
        self._checkpoint_waiting = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- the thread ---------------------------------------------------------------------------

    def start(self, period: float = BEAT_PERIOD) -> None:
        """Start the thread (once)."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._run, args=(period,), name='rory-pulse',
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop the thread: nothing is posted to the executor any more."""
        self._stop.set()

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            try:
                self.tick()
            except Exception:  # a side thread must not die silently: the beat would stop
                _logger.exception('[rory] the pulse failed')

    # -- what it does -------------------------------------------------------------------------

    def schedule_checkpoints(self, interval_s: float, run: Callable[[], None]) -> None:
        """From now on, post ``run`` every ``interval_s`` of the node's clock (at release)."""
        interval_ns = max(1, int(interval_s * 1e9))
        self._checkpoint = (CheckpointSchedule(interval_ns, self._node_now_ns() + interval_ns),
                            run)

    def tick(self) -> None:
        """One look: beat, or probe the executor; post a checkpoint when one is due."""
        progress = self._progress()
        if progress != self._seen_progress:
            # A callback finished since the last look: the executor is alive.
            self._seen_progress = progress
            self._beat()
        elif not self._probe_waiting:
            self._probe_waiting = self._post(self._probe)
        if self._checkpoint is not None and not self._checkpoint_waiting:
            schedule, _ = self._checkpoint
            if schedule.due(self._node_now_ns()):
                self._checkpoint_waiting = self._post(self._run_checkpoint)

    def _post(self, task: Callable[[], None]) -> bool:
        """Hand ``task`` to the executor; False when there is none (yet, or any more)."""
        if self._stop.is_set():
            return False
        executor = self._executor()
        if executor is None:
            return False
        try:
            executor.create_task(task)
        except Exception:  # an executor shut down under it (its guard condition is gone)
            return False
        return True

    def _probe(self) -> None:
        # On the executor's thread: it is running.
        self._probe_waiting = False
        self._beat()

    def _run_checkpoint(self) -> None:
        assert self._checkpoint is not None
        try:
            self._checkpoint[1]()
        finally:
            self._checkpoint_waiting = False
            self._beat()
