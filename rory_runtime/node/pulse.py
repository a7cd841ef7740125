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
  its inputs is never woken for it. An idle one is not woken at every look either: when the
  thread the last probe ran on is parked in rclpy's wait for work (:func:`executor_parked`:
  its top frame is the executor's ``wait_set.wait`` call), nothing of the node's is running and
  the executor is alive and idle, so the thread beats for it, and probes only every
  :data:`PARKED_PROBE_EVERY` looks, to prove the parked executor still wakes.
* **schedules checkpoints** on the node's own clock (ROS time: simulation time when the node
  uses it, so a /clock that stands still takes none, as a timer would not fire): when one is
  due it posts the checkpoint (or, for the replay method, the log rotation) to the executor the
  same way, one at a time.

:class:`Pulse` is driven by :meth:`Pulse.tick`, which the thread calls; tests call it with fakes
for the executor and the clocks (tests/runtime/test_pulse.py).
"""

from __future__ import annotations

import inspect
import logging
import sys
import threading
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from types import CodeType
from typing import Protocol

_logger = logging.getLogger('rory.pulse')

BEAT_PERIOD = 0.2
"""Seconds between the thread's looks (the supervisor's hang_timeout is far longer; a beat 3
periods late already makes it keep the node's inputs: supervisor/watchdog.py)."""


PARKED_PROBE_EVERY = 10
"""Looks between two probes of an executor found parked in its wait (2 s at
:data:`BEAT_PERIOD`): a parked executor that no longer wakes stops the beat within that, far
inside the supervisor's hang_timeout."""


@cache
def _wait_call() -> tuple[CodeType, int] | None:
    """Where rclpy's executor blocks waiting for work: the code of
    ``Executor._wait_for_ready_callbacks`` and the line of its ``wait_set.wait`` call; None if
    this rclpy has no such line (then an idle node is probed at every look, as before)."""
    from rclpy.executors import Executor

    function = Executor._wait_for_ready_callbacks
    try:
        lines, first = inspect.getsourcelines(function)
    except (OSError, TypeError):
        return None
    for offset, text in enumerate(lines):
        if 'wait_set.wait(' in text:
            return function.__code__, first + offset
    return None


def executor_parked(thread_id: int) -> bool:
    """Whether thread ``thread_id`` is blocked in rclpy's executor wait, waiting for work (so no
    callback is running on it)."""
    call = _wait_call()
    frame = sys._current_frames().get(thread_id)
    return (call is not None and frame is not None and frame.f_code is call[0]
            and frame.f_lineno == call[1])


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
        parked: Whether a thread (by id) is parked in the executor's wait for work.
    """

    def __init__(self, executor: Callable[[], TaskRunner | None], beat: Callable[[], None],
                 progress: Callable[[], int], node_now_ns: Callable[[], int],
                 parked: Callable[[int], bool] = executor_parked) -> None:
        self._executor = executor
        self._beat = beat
        self._progress = progress
        self._node_now_ns = node_now_ns
        self._parked = parked
        self._seen_progress = -1
        self._probe_waiting = False
        # The thread the last probe ran on (the executor's), and looks since a probe was posted.
        self._executor_thread: int | None = None
        self._looks_since_probe = 0
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
        self._looks_since_probe += 1
        if progress != self._seen_progress:
            # A callback finished since the last look: the executor is alive.
            self._seen_progress = progress
            self._beat()
        elif self._probe_waiting:
            pass  # the probe beats when it runs; until then, no beat
        elif (self._executor_thread is not None and self._looks_since_probe < PARKED_PROBE_EVERY
              and self._parked(self._executor_thread)):
            self._beat()  # idle: parked in its wait, nothing of the node's running
        else:
            self._probe_waiting = self._post(self._probe)
            self._looks_since_probe = 0
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
        self._executor_thread = threading.get_ident()
        self._probe_waiting = False
        self._beat()

    def _run_checkpoint(self) -> None:
        assert self._checkpoint is not None
        try:
            self._checkpoint[1]()
        finally:
            self._checkpoint_waiting = False
            self._beat()
